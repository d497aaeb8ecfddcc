"""A CT volume in memory: Hounsfield units on a voxel grid placed in the patient's LPS frame."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Volume:
    """One CT (or one phase of a 4D CT).

    `hu` is int16 with shape (nz, ny, nx), indexed [k, j, i]. `T_ct_from_voxel` maps voxel
    indices (i, j, k, 1), voxel centres at integer indices, into the `ct` frame of
    DESIGN.md (DICOM LPS, mm); it carries spacing, direction and origin.
    """

    hu: np.ndarray
    T_ct_from_voxel: np.ndarray
    source: str = ""

    @property
    def shape_xyz(self) -> tuple[int, int, int]:
        nz, ny, nx = self.hu.shape
        return nx, ny, nz

    @property
    def spacing_mm(self) -> np.ndarray:
        """Voxel size along i, j, k (mm)."""
        return np.linalg.norm(self.T_ct_from_voxel[:3, :3], axis=0)


#: The lowest CT number a scanner's reconstruction holds (12-bit HU scale, -1024 to 3071).
#: Anything below is not tissue but padding: voxels outside the reconstruction circle
#: (DICOM PixelPaddingValue, often -2000 or -3024 HU) or a vendor's "no data" marker.
CT_SCALE_MIN_HU = -1024
#: What padding is read as: air, density zero on the HU -> density line (1 + HU/1000).
PADDING_AS_HU = -1000


def padding_as_air(hu: np.ndarray) -> np.ndarray:
    """`hu` with every voxel below CT_SCALE_MIN_HU set to air (PADDING_AS_HU), in its own
    dtype; `hu` itself when there are none. Left as it is, -3024 HU would be a density of
    -2 g/cm^3 wherever a sample blends it with the body cut at the circle's edge, and would
    cancel the tissue beside it."""
    pad = hu < CT_SCALE_MIN_HU
    if not pad.any():
        return hu
    return np.where(pad, hu.dtype.type(PADDING_AS_HU), hu)
