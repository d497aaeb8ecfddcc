"""A training case: the (4D) CT of a virtual patient, where it lies in the box, and its materials."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from . import limits
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


#: Anatomical roles a label map may name (label ids per role) for the breathing motion.
RESPIRATION_ROLES = ("lungs", "liver", "spine", "ribs", "diaphragm")


class Respiration(Section):
    """Controllable breathing (the PTC simulator's two muscle groups, section 2.2 of its paper).

    With f = rate_per_min / 60: ribs turn by max * 1/2 (1 + sin(2 pi f t)), the central
    tendon moves by diaphragm_mm / 2 * sin(2 pi f t) about its mid position, so
    end-inspiration is at t = 1/(4f) + k/f and end-expiration at t = 3/(4f) + k/f.
    """

    diaphragm_mm: float = Field(
        15.0, ge=0, le=80,
        description="The central tendon's excursion, end-expiration to end-inspiration, superior-inferior (mm).")
    rib_gamma_deg: float = Field(
        2.0, ge=0, le=15,
        description="Peak lateral-excursion (bucket-handle) rotation of each rib about its costovertebral joint (deg).")
    rib_lambda_deg: float = Field(
        3.0, ge=0, le=15,
        description="Peak anteroposterior (pump-handle) rotation of each rib about its costovertebral joint (deg).")
    rate_per_min: float = Field(15.0, ge=0, le=60, description="Breaths per minute; 0 = held.")
    intercostal_share: float | None = Field(
        None, ge=0, le=1, description="Share of the breath the rib cage does (0-1, e.g. 0.75 or 0 for diaphragm alone); the ribs then "
                                      "turn by rib_*_deg x share / 0.5 and the tendon by diaphragm_mm x (1 - share) / 0.5, so 0.5 "
                                      "keeps the given amplitudes. Omit: the amplitudes as given.")
    label_map: str | None = Field(None, description="Optional label map (NIfTI/MHA) on the CT's grid, relative to this profile.")
    labels: dict[Literal[RESPIRATION_ROLES], list[int]] | None = Field(  # type: ignore[valid-type]  # the tuple's names
        None, description="Label ids per role (lungs, liver, spine, ribs, diaphragm) in label_map; an empty or missing role is "
                          "found from the HU thresholds instead.")
    irregularity: float = Field(
        0.0, ge=0, le=0.5,
        description="Breath-to-breath variation: each breath (end-expiration to end-expiration) lasts the rate's breath "
                    "times 1 + irregularity x u and goes to the depth times 1 + irregularity x v, with u and v drawn "
                    "in -1..1 for that breath; 0 = regular, and the contract's end-inspiration/expiration times hold "
                    "(fraction).")
    irregularity_seed: int = Field(
        0, ge=0, description="Seed of the breath-to-breath draws: the same seed, the same irregular breathing (count).")
    rate_step_per_min: float = Field(3.0, gt=0, le=20, description="Faster/slower keys change the rate by this (breaths/min).")
    rate_max_per_min: float = Field(40.0, gt=0, le=80, description="Fastest rate the console allows: hyperventilation (breaths/min).")
    depth_step: float = Field(
        0.25, gt=0, le=1,
        description="Deeper/shallower keys change the depth by this (fraction of the profile's amplitudes).")
    depth_max: float = Field(2.0, ge=1, le=4, description="Deepest breath the console allows (multiple of the profile's amplitudes).")
    depth_ramp_s: float = Field(1.0, gt=0, le=10, description="A depth change is eased in over this time, so the anatomy never jumps (s).")
    abdomen_falloff_mm: float = Field(
        150.0, gt=0, le=400,
        description="Below the lowest point of the diaphragm the organs' displacement falls linearly to 0 over this "
                    "distance (mm).")
    lateral_blur_mm: float = Field(
        12.0, ge=0, le=60,
        description="The moving region is the lungs' footprint in the axial plane, softened by a Gaussian of this sigma "
                    "(mm), so the body wall outside it stays still.")
    spine_half_width_mm: float = Field(
        28.0, gt=0, le=80,
        description="Without spine labels: bone within this distance of the midline, behind the body's centre, is the "
                    "(still) spine (mm).")
    rib_head_max_mm: float = Field(
        6.0, gt=0, le=100,
        description="Without rib labels: a bone piece whose nearest point lies within this of the spine is a rib (mm); "
                    "others stay still.")
    rib_min_length_mm: float = Field(
        40.0, gt=0, le=300,
        description="Without rib labels: a piece reaching less far than this from its joint (a transverse process) is not "
                    "a rib (mm).")
    rib_pleura_max_mm: float | None = Field(
        None, gt=0, le=60,
        description="Without rib labels, for a CT whose scapulae touch the upper ribs: behind the body's centre and above "
                    "the domes, rib bone lies within this of the lungs (mm), or within rib_neck_mm of the spine; the "
                    "scapula lies outside the cage beyond its muscles and stays still. Omit (the default): rib_max_height_mm "
                    "alone tells the ribs from the scapulae; this rule cuts ribs that run farther from the lungs than this.")
    rib_neck_mm: float = Field(
        25.0, gt=0, le=80,
        description="With rib_pleura_max_mm: between the spine and the lungs, the ribs' necks are the bone within this of "
                    "the spine (mm); keep it below the scapula's distance from the spine.")
    rib_max_height_mm: float | None = Field(
        15.0, gt=0, le=200,
        description="Without rib labels: bone standing in unbroken vertical runs taller than this (mm) is a plate, a "
                    "scapula or the sternum, and stays still; a rib, a thin tube running round the chest, is lower "
                    "(its height over the cosine of its slope). This cuts a scapula that touches the upper ribs off "
                    "them. Keep it above the ribs' height and below the scapulae's; omit (null) to take every bone "
                    "piece that reaches the spine.")
    rib_plate_widen_mm: float = Field(
        3.0, ge=0, le=20,
        description="With rib_max_height_mm: bone is widened by this in each axial slice before its vertical runs are "
                    "measured, so a thin plate that leans or curves still stands tall (mm).")
    rib_below_dome_mm: float = Field(
        30.0, ge=0, le=200,
        description="Without rib labels: rib joints lie no lower than this below the diaphragm's lowest point, which "
                    "keeps the pelvis out (mm).")
    bone_fill_hu: float = Field(
        40.0, ge=-200, le=200,
        description="What a bone voxel becomes in the soft tissue that moves under it (HU, muscle).")
    ct_end_expiration_s: float | None = Field(
        None, ge=0, description="A 4D CT only: the time stamp of its end-expiration phase (s); its phases span one breath "
                                "(breathing.period_s), and only rate and depth act on it.")
    depth_states: int = Field(
        6, ge=2, le=16,
        description="Breathing states the appliance precomputes between end-expiration and the deepest breath, blended in "
                    "projection space.")

    def problems(self) -> Findings:
        if self.rate_per_min > self.rate_max_per_min:
            yield ("rate_per_min",), f"must not exceed rate_max_per_min ({self.rate_max_per_min:g} breaths/min)"
        if self.labels and self.label_map is None:
            yield ("labels",), "needs label_map: the file the label ids are in"


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
    respiration: Respiration | None = Field(None, description="Controllable breathing applied to the CT (see Respiration).")
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
        offset = sum(x * x for x in (row[3] for row in self.T_phantom_from_ct[:3])) ** 0.5
        if offset > limits.MAX_PLACEMENT_OFFSET_MM:
            yield (("T_phantom_from_ct",), f"puts the CT {limits.fmt(offset)} mm from the phantom's origin; a patient in "
                                           f"the box lies within {limits.MAX_PLACEMENT_OFFSET_MM:g} mm")
        if self.respiration is not None:
            if self.phases is not None and len(self.phases) > 1:
                if self.respiration.ct_end_expiration_s is None:
                    yield ("respiration", "ct_end_expiration_s"), ("is required for a 4D CT: the time stamp of its "
                                                                   "end-expiration phase")
                elif self.respiration.ct_end_expiration_s not in [p.time_s for p in self.phases]:
                    yield ("respiration", "ct_end_expiration_s"), "must be the time_s of one of the phases"
            if self.builtin is not None and self.respiration.label_map:
                yield ("respiration", "label_map"), "the built-in patient is segmented from its HU; leave out label_map"
            for loc, message in self.respiration.problems():
                yield ("respiration", *loc), message
        m = self.materials
        if not m.air_max_hu < m.bone_min_hu:
            yield ("materials", "bone_min_hu"), "must be greater than materials.air_max_hu"
        if not m.bone_min_hu < 1000:
            yield ("materials", "bone_min_hu"), "must be below 1000 HU (bone density is given at 1000 HU)"
        if m.contrast_min_hu is not None and not m.contrast_min_hu > m.bone_min_hu:
            yield ("materials", "contrast_min_hu"), "must be greater than materials.bone_min_hu"
        if m.contrast_min_hu is not None and self.contrast is None:
            yield ("contrast",), "is required when materials.contrast_min_hu is set (which agent, what concentration)"
