"""The fluoroscope profile's `ct_sampling` section: how the renderer samples the CT's voxels
along each ray (appliance/xray/drr.cl, Joseph's method)."""

from __future__ import annotations

from pydantic import Field

from .base import Section


class CtSampling(Section):
    voxel_edge_px: float | None = Field(
        4.0, gt=0, le=64,
        description="Where a CT voxel is larger than this many display pixels (its footprint at the ray's depth, "
                    "across the beam), a ray's sample of it passes to the next voxel over this width, centred on the "
                    "faces the two share, instead of over the whole voxel (display pixels). 1 is the voxel grid as it "
                    "is, piecewise constant, averaged over the detector pixel: what the grid's exact line integral "
                    "(Siddon) shows, so a thick-slice CT at high zoom keeps its edges instead of 10-pixel ramps; wider "
                    "softens the steps a coarse grid shows at the cost of that agreement (4: the shipped profiles'). "
                    "Voxels no larger than this are interpolated linearly (Joseph), which keeps small voxels from "
                    "aliasing. None: linear interpolation everywhere, whatever the voxel's size.")
