"""The appliance profile's `rendering` section: what a frame may reuse, and which matrix it gets."""

from __future__ import annotations

from pydantic import Field

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
        "the full one (pixels); none: always the full matrix.")
    settle_s: float = Field(
        0.12, ge=0, le=5, description="The pose must stay unchanged this long before the full matrix is rendered (s).")
    crossfade_s: float = Field(
        0.0, ge=0, le=5, description="After the switch to the full matrix its image is blended into the last moving one "
        "over this long (s); for a fluoroscope without a recursive filter, which otherwise hides the switch.")
