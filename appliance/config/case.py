"""A training case: the (4D) CT of a virtual patient, where it lies in the box, and its materials."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from .base import IDENTITY, Findings, RigidTransform, Section

#: Procedurally generated patients that ship with the appliance (see appliance/patient/).
BUILTIN_PATIENTS = ("child-torso",)


class Phase(Section):
    volume: str = Field(min_length=1, description="DICOM series folder, NIfTI (.nii/.nii.gz) or MHA/NRRD file, relative to this profile.")
    time_s: float = Field(ge=0, description="Time stamp of this phase in the case timeline (s).")


class Materials(Section):
    """How Hounsfield units become materials and densities for the X-ray physics."""

    air_max_hu: float = Field(-800.0, description="Voxels at or below this are air (HU).")
    bone_min_hu: float = Field(300.0, description="Voxels at or above this are bone; between the two, soft tissue (HU).")
    contrast_min_hu: float | None = Field(
        None, description="Voxels at or above this are iodinated contrast rather than bone (HU); omit for cases without contrast.")
    bone_density_at_1000_hu_g_per_cm3: float = Field(
        1.6, gt=1, le=3, description="Bone density at 1000 HU (g/cm^3); bone density is linear in HU from the soft-tissue "
                                     "value (1 + HU/1000) at bone_min_hu to this.")


class Contrast(Section):
    agent: Literal["iodine"] = Field("iodine", description="Contrast element.")
    concentration_mg_per_ml: float = Field(gt=0, le=400, description="Iodine concentration in the filled organ (mg/mL).")


class Breathing(Section):
    period_s: float = Field(gt=0, le=30, description="One breath (s); the phases span one cycle.")


class Patient(Section):
    """The virtual patient's demographics, as dose reports (IHE REM) require them."""

    sex: Literal["M", "F", "O"] = Field("O", description="M, F or O (other/unknown), as DICOM Patient's Sex.")
    age_years: int = Field(30, ge=0, le=130, description="Age at the time of the case (years).")
    weight_kg: float = Field(70.0, gt=0, le=500, description="Body mass (kg).")
    height_m: float = Field(1.70, gt=0, le=3, description="Body height (m).")


class CaseProfile(Section):
    title: str = Field(min_length=1, description="Shown on screen and recorded with each session.")
    description: str = Field("", description="What the trainee should practise.")
    builtin: Literal[BUILTIN_PATIENTS] | None = Field(  # type: ignore[valid-type]  # the tuple's names
        None, description="Use a built-in generated patient instead of `phases`.")
    phases: list[Phase] | None = Field(None, description="The CT volumes with their time stamps, in time order.")
    at_end: Literal["loop", "hold"] = Field("loop", description="After the last phase: start again, or stay on it.")
    T_phantom_from_ct: RigidTransform = Field(IDENTITY, description="Where the CT lies in the box phantom's frame (4x4, mm).")
    materials: Materials = Field(default_factory=Materials)
    contrast: Contrast | None = None
    breathing: Breathing | None = None
    patient: Patient = Field(default_factory=Patient, description="Demographics recorded in dose reports.")

    def problems(self) -> Findings:
        if (self.builtin is None) == (self.phases is None):
            yield ("phases",), "give either `phases` (your CT volumes) or `builtin` (a generated patient), not both or neither"
        if self.phases is not None:
            if not self.phases:
                yield ("phases",), "must list at least one volume"
            for i in range(1, len(self.phases or [])):
                if not self.phases[i].time_s > self.phases[i - 1].time_s:
                    yield ("phases", i, "time_s"), f"must be later than phases[{i - 1}].time_s ({self.phases[i - 1].time_s} s)"
        m = self.materials
        if not m.air_max_hu < m.bone_min_hu:
            yield ("materials", "bone_min_hu"), "must be greater than materials.air_max_hu"
        if not m.bone_min_hu < 1000:
            yield ("materials", "bone_min_hu"), "must be below 1000 HU (bone density is given at 1000 HU)"
        if m.contrast_min_hu is not None and not m.contrast_min_hu > m.bone_min_hu:
            yield ("materials", "contrast_min_hu"), "must be greater than materials.bone_min_hu"
        if m.contrast_min_hu is not None and self.contrast is None:
            yield ("contrast",), "is required when materials.contrast_min_hu is set (which agent, what concentration)"
