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
