"""Whether a DICOM series, MetaImage or NRRD volume is a CT in HU, from a few of its slices, so
`fluorosim validate` catches a label map or a CT stored without its rescale intercept in a
moment instead of at load, when the demo is about to start.

A NIfTI needs none of this: `volume_checks.check_header` already counts its bytes and sees every
voxel. For the others the voxels are compressed, in another file, or spread over a folder, so
this reads `SAMPLED_SLICES` axial slices spread through the volume (through ITK, as the loader
does: DICOM rescale slopes and intercepts and compressed transfer syntaxes are handled alike).
A sample can only raise a suspicion (a CT cropped inside the body may have no air in the
slices read), so whenever the sample is not plainly a CT in HU the whole volume is read and the
load's own check decides: a healthy CT costs a few slices, only a doubtful one a full read.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .volume_checks import check_hu

#: Axial slices read from a volume at validate: enough to meet air around the patient in any
#: CT that has it, few enough that a 500-slice series validates in a fraction of a second.
SAMPLED_SLICES = 5
#: The first bytes of a MetaImage or NRRD file that hold its text header (bytes).
_HEADER_BYTES = 4096


def _spread(count: int) -> list[int]:
    """Up to SAMPLED_SLICES indices spread evenly through 0..count-1, the ends excluded where
    possible (a first or last slice may be a padded one)."""
    if count <= SAMPLED_SLICES:
        return list(range(count))
    return sorted({int(round((n + 1) * (count - 1) / (SAMPLED_SLICES + 1))) for n in range(SAMPLED_SLICES)})


def _compressed(path: Path) -> bool:
    """Whether a MetaImage or NRRD header says its voxels are compressed (no slice can be read alone)."""
    try:
        with open(path, "rb") as f:
            head = f.read(_HEADER_BYTES).decode("latin-1").lower()
    except OSError:
        return False
    return any(mark in head for mark in ("compresseddata = true", "encoding: gz", "encoding: bz", "encoding: gzip"))


def _file_slices(path: Path) -> np.ndarray:
    import SimpleITK as sitk

    reader = sitk.ImageFileReader()
    reader.SetFileName(str(path))
    reader.ReadImageInformation()
    nx, ny, nz = reader.GetSize()
    if _compressed(path):
        whole = sitk.GetArrayFromImage(reader.Execute())
        return whole[_spread(nz)]
    slices = []
    for k in _spread(nz):
        reader.SetExtractIndex((0, 0, k))
        reader.SetExtractSize((nx, ny, 1))
        slices.append(sitk.GetArrayFromImage(reader.Execute()))
    return np.concatenate(slices)


def _series_slices(files: list[Path]) -> np.ndarray:
    import SimpleITK as sitk

    return np.concatenate([sitk.GetArrayFromImage(sitk.ReadImage(str(files[k]))).reshape(-1)
                           for k in _spread(len(files))])


def _whole(path: Path, files: list[Path] | None) -> np.ndarray:
    import SimpleITK as sitk

    if files is None:
        return sitk.GetArrayFromImage(sitk.ReadImage(str(path)))
    reader = sitk.ImageSeriesReader()
    reader.SetFileNames([str(f) for f in files])
    return sitk.GetArrayFromImage(reader.Execute())


def check_sampled_hu(path: Path, files: list[Path] | None = None) -> tuple[list[str], list[str]]:
    """(errors, warnings) about the values of the volume at `path` (a MetaImage/NRRD file, or a
    DICOM series folder whose slice files, in order, are `files`), as the load's check_hu would
    give them, without the file name. Voxels the sample cannot read are read whole, as the load
    reads them; voxels that cannot be read at all (a truncated file) are refused as the load would."""
    from .volume_io import _stderr_captured

    failure: Exception | None = None
    with _stderr_captured() as said:
        try:
            sample = _file_slices(path) if files is None else _series_slices(files)
        except (RuntimeError, OSError, ValueError):
            sample = None       # some readers extract no slice alone: the whole read decides
        try:
            if sample is not None:
                errors, warnings = check_hu(sample)
                if not errors and not warnings:
                    return [], []
            return check_hu(_whole(path, files))
        except (RuntimeError, OSError, ValueError) as e:
            failure = e
    told = said() or str(failure).strip().splitlines() or ["unreadable voxels"]
    reason = told[0] if said() else told[-1]      # ITK's own line, else the exception's last
    return [f"cannot read this volume's voxels ({reason[:160]}); check the file is complete and not corrupt"], []
