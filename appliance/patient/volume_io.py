"""Loading CT volumes: a DICOM series folder, NIfTI (.nii, .nii.gz), MetaImage (.mha, .mhd) or NRRD.

SimpleITK reads the pixels and the physical frame (origin, spacing, direction, in LPS mm as
ITK reports for every format); pydicom reads the DICOM headers so a folder holding a mixed,
gappy or unevenly spaced series is refused with one line saying what is wrong, instead of
being stacked into a distorted patient.
"""

from __future__ import annotations

import contextlib
import logging
import os
import sys
import tempfile
from pathlib import Path

import numpy as np

from ..errors import FluorosimError
from .volume import Volume, padding_as_air
from .volume_checks import check_header, check_hu, check_spacing
from .volume_sampling import check_sampled_hu

log = logging.getLogger(__name__)

FILE_SUFFIXES = (".nii", ".nii.gz", ".mha", ".mhd", ".nrrd", ".nhdr")
#: Slice gaps may differ from the series' median gap by this fraction before the series is
#: called uneven (rounding in the scanner's position values stays far below it).
SPACING_TOLERANCE = 0.05


def load_volume(path: str | Path, *, hu_checked: bool = True) -> Volume:
    """The CT at `path` as HU on its voxel grid in the `ct` (LPS, mm) frame.

    `hu_checked=False` reads values that are not HU of a CT (a label map, raw scanner values)
    as they are, for `case inspect` to say what they look like; rendering always checks."""
    p = Path(path)
    if not p.exists():
        raise FluorosimError(f"{p}: no such file or folder; give a DICOM series folder, a NIfTI, MHA or NRRD file")
    if p.is_dir():
        return load_dicom_series(p, hu_checked=hu_checked)
    name = p.name.lower()
    if not name.endswith(FILE_SUFFIXES):
        if name.endswith(".dcm"):
            raise FluorosimError(f"{p}: a single DICOM file; give the folder that holds the whole series")
        raise FluorosimError(f"{p}: unknown volume format; use a DICOM series folder, .nii/.nii.gz, .mha/.mhd or .nrrd")
    import SimpleITK as sitk

    _refuse_or_warn(str(p), (check_header(p, hu_checked)[0], []))  # its warnings come again from the loaded image
    with _stderr_captured() as said:
        try:
            image = sitk.ReadImage(str(p))
        except RuntimeError:
            image = None
    if image is None:
        reason = said()[0] if said() else "unreadable"
        raise FluorosimError(f"{p}: cannot read this volume ({reason[:160]}); check the file is complete and not corrupt")
    return _from_image(image, str(p), hu_checked)


def _refuse_or_warn(source: str, found: tuple[list[str], list[str]]) -> None:
    """Raise the first error of a check as one line naming the volume; log its warnings."""
    errors, warnings = found
    if errors:
        raise FluorosimError(f"{source}: {errors[0]}")
    for warning in warnings:
        log.warning("%s: %s", source, warning)


@contextlib.contextmanager
def _stderr_captured():
    """Collect what ITK's C++ readers print straight to file descriptor 2, so a bad file
    gives our one line instead of their several; yields a function returning those lines."""
    sys.stderr.flush()
    saved = os.dup(2)
    lines: list[str] = []
    with tempfile.TemporaryFile(mode="w+b") as tmp:
        os.dup2(tmp.fileno(), 2)
        try:
            yield lambda: lines
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            tmp.seek(0)
            text = tmp.read().decode("utf-8", "replace")
            lines.extend(l.strip() for l in text.splitlines() if l.strip())


def _from_image(image, source: str, hu_checked: bool = True) -> Volume:
    import SimpleITK as sitk

    if image.GetDimension() != 3:
        raise FluorosimError(f"{source}: a {image.GetDimension()}D image; give each CT phase as its own 3D volume")
    if image.GetNumberOfComponentsPerPixel() != 1:
        raise FluorosimError(f"{source}: has {image.GetNumberOfComponentsPerPixel()} components per voxel; a CT has one (HU)")
    arr = sitk.GetArrayFromImage(image)      # (nz, ny, nx)
    if not np.issubdtype(arr.dtype, np.number):
        raise FluorosimError(f"{source}: voxels are not numbers")
    if hu_checked:
        _refuse_or_warn(source, check_hu(arr))
    if arr.dtype != np.int16:
        arr = np.clip(np.rint(arr), -32768, 32767).astype(np.int16)
    arr = padding_as_air(arr)
    spacing = np.array(image.GetSpacing(), dtype=np.float64)
    if np.any(spacing <= 0):
        raise FluorosimError(f"{source}: voxel spacing {tuple(spacing)} mm must be positive")
    _refuse_or_warn(source, check_spacing(spacing))
    direction = np.array(image.GetDirection(), dtype=np.float64).reshape(3, 3)
    T = np.eye(4)
    T[:3, :3] = direction @ np.diag(spacing)
    T[:3, 3] = image.GetOrigin()
    if abs(abs(np.linalg.det(direction)) - 1) > 1e-3:
        raise FluorosimError(f"{source}: the header's direction cosines are not orthonormal")
    return Volume(hu=np.ascontiguousarray(arr), T_ct_from_voxel=T, source=source)


def load_dicom_series(folder: Path, *, hu_checked: bool = True) -> Volume:
    """One CT series from a folder: sorted by ImagePositionPatient along the slice normal,
    RescaleSlope/Intercept applied; mixed series, missing or uneven slices refused.
    `hu_checked=False` as for `load_volume` (a label map exported as an image series)."""
    import SimpleITK as sitk

    headers, normal, step = dicom_series_headers(folder)

    reader = sitk.ImageSeriesReader()
    reader.SetFileNames([str(f) for f, _ in headers])
    with _stderr_captured() as said:
        try:
            image = reader.Execute()
        except RuntimeError as e:
            image, error = None, str(e)
    if image is None:
        reason = (said() or error.strip().splitlines() or ["unreadable"])[-1]
        raise FluorosimError(f"{folder}: cannot read the DICOM pixels ({reason[:160]})")
    # ITK takes the slice spacing from the positions; make the frame agree with our sort.
    vol = _from_image(image, str(folder), hu_checked)
    T = vol.T_ct_from_voxel.copy()
    first = np.array([float(x) for x in headers[0][1].ImagePositionPatient])
    T[:3, 2] = normal * step
    T[:3, 3] = first
    return Volume(hu=vol.hu, T_ct_from_voxel=T, source=str(folder))


def check_volume(path: Path) -> tuple[list[str], list[str]]:
    """(errors, warnings) of a volume from its headers alone, as `fluorosim validate` reports them;
    the messages name the file or folder."""
    if not path.exists():
        return [f"{path}: no such file or folder"], []
    try:
        if path.is_dir():
            headers, _, step = dicom_series_headers(path)
            errors, warnings = check_spacing([*map(float, headers[0][1].PixelSpacing), step])
            files: list[Path] | None = [f for f, _ in headers]
        else:
            if not path.name.lower().endswith(FILE_SUFFIXES):
                load_volume(path)  # raises the one line for an unknown or single-DICOM file
            errors, warnings = check_header(path)
            files = None
        if not errors and not path.name.lower().endswith((".nii", ".nii.gz")):   # a NIfTI's voxels were scanned
            errors, more = check_sampled_hu(path, files)
            warnings = warnings + more
    except FluorosimError as e:
        return [str(e)], []
    return [f"{path}: {m}" for m in errors], [f"{path}: {m}" for m in warnings]


def dicom_series_headers(folder: Path):
    """The headers of one complete, evenly spaced CT series in `folder`, sorted along the slice
    normal, with that normal and the slice step (mm); a mixed or gappy series is refused."""
    import pydicom

    files = sorted(f for f in folder.iterdir() if f.is_file() and not f.name.startswith("."))
    headers = []
    for f in files:
        try:
            ds = pydicom.dcmread(f, stop_before_pixels=True)
        except Exception:      # pydicom raises several types for a non-DICOM file; skip those files
            continue
        if "PixelData" in ds or hasattr(ds, "ImagePositionPatient"):
            headers.append((f, ds))
    if not headers:
        raise FluorosimError(f"{folder}: no DICOM images found; give the folder holding one CT series")
    series = sorted({str(getattr(ds, "SeriesInstanceUID", "")) for _, ds in headers})
    if len(series) > 1:
        raise FluorosimError(f"{folder}: holds {len(series)} DICOM series (mixed series); "
                             "put each series in its own folder and name the one to load")
    for f, ds in headers:
        for tag in ("ImagePositionPatient", "ImageOrientationPatient", "PixelSpacing", "Rows", "Columns"):
            if not hasattr(ds, tag):
                raise FluorosimError(f"{f}: DICOM image lacks {tag}; it is not a CT slice that can be stacked")
    orient = np.array([float(x) for x in headers[0][1].ImageOrientationPatient])
    size = (int(headers[0][1].Rows), int(headers[0][1].Columns))
    for f, ds in headers[1:]:
        if not np.allclose([float(x) for x in ds.ImageOrientationPatient], orient, atol=1e-4):
            raise FluorosimError(f"{f}: slice orientation differs from the rest of the series (mixed series)")
        if (int(ds.Rows), int(ds.Columns)) != size:
            raise FluorosimError(f"{f}: {ds.Rows}x{ds.Columns} pixels, the series has {size[0]}x{size[1]} (mixed series)")
    normal = np.cross(orient[:3], orient[3:])
    pos = np.array([np.dot(normal, [float(x) for x in ds.ImagePositionPatient]) for _, ds in headers])
    order = np.argsort(pos)
    headers = [headers[i] for i in order]
    pos = pos[order]
    if len(headers) < 2:
        raise FluorosimError(f"{folder}: a single slice; a CT volume needs at least two")
    gaps = np.diff(pos)
    if np.any(gaps < 1e-3):
        i = int(np.argmin(gaps))
        raise FluorosimError(f"{headers[i + 1][0]}: same slice position as {headers[i][0].name} ({pos[i]:.2f} mm); "
                             "the folder holds duplicate slices or two series")
    ipp = np.array([[float(x) for x in ds.ImagePositionPatient] for _, ds in headers])
    sideways = ipp - ipp[0] - np.outer(pos - pos[0], normal)
    if np.abs(sideways).max() > 0.01 * max(float(np.median(gaps)), 1e-3) + 1e-3:
        raise FluorosimError(f"{folder}: slices are shifted sideways along the stack (gantry tilt, up to "
                             f"{np.abs(sideways).max():.2f} mm); resample the series to an untilted grid first")
    step = float(np.median(gaps))
    bad = np.flatnonzero(np.abs(gaps - step) > SPACING_TOLERANCE * step)
    if bad.size:
        i = int(bad[0])
        ratio = gaps[i] / step
        what = (f"about {round(ratio) - 1} missing slice(s)" if ratio > 1.5 and abs(ratio - round(ratio)) < SPACING_TOLERANCE
                else "uneven slice spacing")
        raise FluorosimError(f"{folder}: {what} between slice positions {pos[i]:.2f} and {pos[i + 1]:.2f} mm "
                             f"(gap {gaps[i]:.2f} mm, series spacing {step:.2f} mm); export the complete series")
    return headers, normal, step
