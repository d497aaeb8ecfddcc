"""The appliance profile's `rendering` section: what a frame may reuse, and which matrix it gets."""

from __future__ import annotations

from pydantic import Field, model_validator

from .base import Section


class Rendering(Section):
    """Projection cache and progressive resolution (appliance/xray/projection_cache.py, progressive.py)."""

    cache_pose_tolerance_px: float = Field(
        0.25, ge=0, le=4, description="A pose that moves no corner of the patient's content box by more than this on the "
        "detector counts as unchanged, and the cached line integrals are reused (pixels of the rendered matrix).")
    cache_max_phases: int = Field(
        12, ge=1, le=64, description="Phases whose line integrals are kept for the current pose (count); each costs "
        "16 bytes per pixel of the matrix.")
    moving_matrix_px: int | None = Field(
        None, ge=64, le=8192, description="While the C-arm moves, render this square matrix and show it scaled up to "
        "the full one (pixels); none: always the full matrix. With moving_matrix_min_px, the largest moving matrix.")
    moving_matrix_min_px: int | None = Field(
        None, ge=64, le=8192, description="The smallest matrix a moving frame may drop to when a larger one cannot keep "
        "frame_budget_ms (appliance/xray/matrix_control.py); none: moving frames are always moving_matrix_px (pixels).")
    moving_matrix_step_px: int = Field(
        32, ge=8, le=1024, description="Step between the moving matrices, from moving_matrix_px down to "
        "moving_matrix_min_px (pixels).")
    frame_budget_ms: float = Field(
        40.0, gt=0, le=1000, description="What one moving frame may take, from the start of its render to the image on "
        "screen, for the moving matrix to hold: 40 ms is 25 frames/s (ms).")
    matrix_window_frames: int = Field(
        6, ge=2, le=100, description="Moving frames at one matrix whose median frame time decides a step to another "
        "(count); a step starts the count again.")
    matrix_step_up_margin: float = Field(
        0.8, gt=0, lt=1, description="A larger moving matrix is taken only when this one's median frame time, scaled "
        "by the larger one's pixel count, is within this fraction of frame_budget_ms; below 1 so that frame-to-frame "
        "noise does not make the matrix hunt (dimensionless).")
    slab_max_shift_px: float | None = Field(
        None, ge=0, le=16, description="Moving frames are cast through pre-integrated slabs (pairs of slices averaged "
        "along the ray's dominant axis, half the samples; appliance/xray/slabs.py) where the rays move less than this "
        "across a slab, seen on the detector: the whole field where its steepest ray does, else each 16-pixel packet "
        "all of whose rays do (the packet kernel), and slabs of four slices in the middle where they allow those; "
        "none: never (pixels of the moving matrix).")
    rest_slab_max_shift_px: float | None = Field(
        None, ge=0, le=16, description="A held view (the full matrix at rest, and the rest matrix) is cast through the "
        "same slabs by the same rule at this shift across a slab, seen on the detector: a shift within the "
        "detector's own point-spread does not show; none: through the full volume (pixels of the matrix cast).")
    slab_phases: int = Field(
        4, ge=1, le=64, description="Slab copies kept on the device, one per phase and axis, each half a phase's size "
        "(count).")
    settle_s: float = Field(
        0.12, ge=0, le=5, description="The pose must stay unchanged this long before the full matrix is rendered (s).")
    refine_bands: int | None = Field(
        None, ge=1, le=64, description="At rest, the full matrix is cast beside the live frames, on a thread of its own "
        "in this many bands of rows (the live frames take the device between bands), while the moving matrix's "
        "cached image stays on screen; none: the full matrix is cast within the frame that first shows it (count).")
    rest_matrix_px: int | None = Field(
        None, ge=64, le=8192, description="At rest, the view is first cast and shown at this square matrix, then at the "
        "full one (daemon.render_matrix_px, or the detector's native matrix): a sharp view a few hundred ms sooner "
        "where the full matrix's cast takes longer. Needs refine_bands; a phase new to a held view is shown at this "
        "matrix while the full one casts it. None, or not below the full matrix: straight to the full one (pixels).")
    rest_hold_px: float | None = Field(
        None, gt=0, le=16, description="Once the pose has rested settle_s, the view is held at that pose while the "
        "tracked pose stays within this of it (the tracker's jitter and its filter's creep as the C-arm stops), so a "
        "held view keeps its full matrix and does not shimmer; a larger move is motion again. More than "
        "cache_pose_tolerance_px; none: any change beyond that tolerance is motion (pixels of the rendered matrix).")
    crossfade_s: float = Field(
        0.0, ge=0, le=5, description="After the switch to the full matrix its image is blended into the last moving one "
        "over this long (s); for a fluoroscope without a recursive filter, which otherwise hides the switch.")

    @model_validator(mode="after")
    def _ladder(self) -> Rendering:
        low, high = self.moving_matrix_min_px, self.moving_matrix_px
        if low is not None and high is None:
            raise ValueError("moving_matrix_min_px needs moving_matrix_px, the largest moving matrix")
        if low is not None and high is not None and low > high:
            raise ValueError(f"moving_matrix_min_px ({low}) must not exceed moving_matrix_px ({high}): the moving "
                             f"matrices run from moving_matrix_px down to moving_matrix_min_px")
        return self

    @model_validator(mode="after")
    def _rest_matrix(self) -> Rendering:
        if self.rest_matrix_px is not None and self.refine_bands is None:
            raise ValueError(f"rest_matrix_px ({self.rest_matrix_px}) needs refine_bands: the rest matrix and the "
                             f"full one after it are cast beside the live frames")
        return self

    @model_validator(mode="after")
    def _hold(self) -> Rendering:
        hold = self.rest_hold_px
        if hold is not None and hold <= self.cache_pose_tolerance_px:
            raise ValueError(f"rest_hold_px ({hold}) must exceed cache_pose_tolerance_px "
                             f"({self.cache_pose_tolerance_px}): a held view is held against moves the cache "
                             f"would already take for motion")
        return self
