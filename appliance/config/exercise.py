"""A teaching exercise: a case, a briefing, and the images the trainee must take, in order.

Each task names a target in the case's CT coordinates (`ct` frame, LPS, mm: +x the
patient's left, +y posterior, +z superior), what the field must do with it (contain it,
centred within a tolerance, at a zoom, collimated), the projection (the beam's direction,
source to detector, within an angle of a stated one) and when (a window of the case's 4D
timeline). A task is met by a saved image that satisfies all of it while the task is the
current one. References are the published values the report compares the trainee with;
their sources are cited in the profile.
"""

from __future__ import annotations

import math

from pydantic import Field

from .base import Findings, Section

Vector3 = tuple[float, float, float]


class Sphere(Section):
    centre_mm: Vector3 = Field(description="Centre in the CT frame (mm).")
    radius_mm: float = Field(gt=0, le=500, description="Radius (mm).")


class Box(Section):
    min_mm: Vector3 = Field(description="Corner with the smallest x, y, z in the CT frame (mm).")
    max_mm: Vector3 = Field(description="Corner with the largest x, y, z in the CT frame (mm).")


class Target(Section):
    """A region of interest: exactly one of `sphere` or `box`."""

    name: str = Field(min_length=1, description="What it is (e.g. 'bladder neck'), shown to the trainee.")
    sphere: Sphere | None = None
    box: Box | None = None


class FieldRequirement(Section):
    whole_target: bool = Field(False, description="The whole target (every corner of a box, the whole sphere) must lie "
                                                  "inside the irradiated field, not only its centre.")
    centred_within_mm: float | None = Field(None, gt=0, le=500, description="The target's centre must lie this close to "
                                            "the central ray, measured at the target's depth (mm); omit for no limit.")
    zoom: list[int] | None = Field(None, min_length=1, max_length=4, description="Zoom levels allowed (1 widest .. 4); "
                                   "omit for any.")
    collimated: bool = Field(False, description="The blades must be closed in on at least one axis.")
    max_field_area_cm2: float | None = Field(None, gt=0, description="The collimated field at the patient entrance "
                                             "reference point may be at most this large (cm^2); omit for no limit.")


class Projection(Section):
    beam_direction: Vector3 = Field(description="Direction of the beam from the focal spot to the detector in the CT frame "
                                                "(any length; e.g. [0, -1, 0] posterior to anterior, tube under the table).")
    within_deg: float = Field(gt=0, le=180, description="Largest angle allowed between the beam and that direction (degrees).")


class PhaseWindow(Section):
    start_s: float = Field(ge=0, description="Start of the window in the case timeline (s).")
    end_s: float = Field(gt=0, description="End of the window, exclusive (s).")
    period_s: float | None = Field(None, gt=0, description="The case timeline loops with this period (s): the window "
                                   "repeats every period; omit for a case that plays once.")
    label: str = Field("", description="What happens in the window (e.g. 'voiding'), shown to the trainee.")

    def contains(self, t_case_s: float) -> bool:
        t = t_case_s % self.period_s if self.period_s else t_case_s
        return self.start_s <= t < self.end_s


class Task(Section):
    name: str = Field(min_length=1, description="Shown on screen as the current task.")
    instruction: str = Field("", description="What to do, for the briefing and the report.")
    target: Target
    field: FieldRequirement = Field(default_factory=FieldRequirement)
    projection: Projection | None = Field(None, description="Beam direction required; omit for any.")
    phase: PhaseWindow | None = Field(None, description="When in the case timeline the image must be taken; omit for any time.")


class Reference(Section):
    value: float = Field(description="The reference value, in the metric's unit.")
    sd: float | None = Field(None, ge=0, description="Its standard deviation, same unit, where the source gives one.")
    source: str = Field(min_length=1, description="Where the value comes from (author, journal, year).")
    note: str = Field("", description="Whose value it is (e.g. 'trainees', 'attendings').")


#: Metrics an exercise may give references for, with their units (see appliance.teaching.metrics).
REFERENCE_METRICS = {
    "exposures": "count", "blank_exposures": "count", "fluoro_time_s": "s", "air_kerma_mgy": "mGy",
    "dap_gy_cm2": "Gy cm^2", "images_saved": "count", "images_on_target": "count", "images_off_target": "count",
    "collimated_share": "fraction", "mean_field_area_cm2": "cm^2", "pulsed_share": "fraction",
    "time_to_first_on_target_s": "s", "tasks_met": "count",
}


class ExerciseProfile(Section):
    title: str = Field(min_length=1, description="Shown on screen and in reports.")
    case: str = Field(min_length=1, description="The case profile it is written for (configs/cases/*.yaml), relative to this file.")
    briefing: str = Field(min_length=1, description="What the trainee reads before starting.")
    tasks: list[Task] = Field(min_length=1, max_length=50, description="The images to take, in order.")
    references: dict[str, Reference | list[Reference]] = Field(
        default_factory=dict, description="Published values per metric (keys of REFERENCE_METRICS), each with its source.")

    def problems(self) -> Findings:
        for i, task in enumerate(self.tasks):
            t = task.target
            if (t.sphere is None) == (t.box is None):
                yield ("tasks", i, "target"), "give exactly one of `sphere` or `box`"
            if t.box is not None and not all(a < b for a, b in zip(t.box.min_mm, t.box.max_mm)):
                yield ("tasks", i, "target", "box", "max_mm"), "must be greater than min_mm on every axis"
            if task.field.zoom is not None:
                for j, z in enumerate(task.field.zoom):
                    if z not in (1, 2, 3, 4):
                        yield ("tasks", i, "field", "zoom", j), f"must be a zoom level 1..4 (got {z})"
            if task.projection is not None and math.hypot(*task.projection.beam_direction) < 1e-6:
                yield ("tasks", i, "projection", "beam_direction"), "must not be the zero vector"
            ph = task.phase
            if ph is not None:
                if not ph.end_s > ph.start_s:
                    yield ("tasks", i, "phase", "end_s"), f"must be later than start_s ({ph.start_s} s)"
                if ph.period_s is not None and ph.end_s > ph.period_s:
                    yield ("tasks", i, "phase", "end_s"), f"must not exceed period_s ({ph.period_s} s)"
        names = [t.name for t in self.tasks]
        for i, name in enumerate(names):
            if name in names[:i]:
                yield ("tasks", i, "name"), f"'{name}' is already the name of another task"
        for key in self.references:
            if key not in REFERENCE_METRICS:
                yield ("references", key), "unknown metric; one of: " + ", ".join(REFERENCE_METRICS)

