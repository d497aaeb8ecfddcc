"""Whether a volume file is a whole CT in Hounsfield units, before the renderer trusts it.

Two kinds of check. `check_header` reads only what a file's header says (and, for NIfTI,
counts the bytes of its voxel data: ITK pads a truncated NIfTI with zeros without a word,
which would render as a water-filled patient), so `fluorosim validate` can check every
phase of a case in a moment. `check_hu` looks at the voxels once they are loaded: NaN
voxels, a label map or mask given as the CT, or values stored without their rescale
intercept, none of which is a CT in HU.

Each returns (errors, warnings) as one-line messages without the file name; the caller
prefixes where the volume came from.
"""

from __future__ import annotations

import gzip
import math
import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

#: Voxel spacing outside these is no CT: a scanner's finest detector row is about 0.2 mm
#: (micro-CT reaches 0.01) and its thickest reconstruction 10 mm (a 30 mm one is a typo) (mm).
SPACING_REFUSED_MM = (0.01, 30.0)
#: Spacing outside these is possible (micro-CT, a thick scout) but unusual enough to say so (mm).
SPACING_USUAL_MM = (0.2, 10.0)
#: Air is -1000 HU and a patient's lungs, fat or the air around the body lie below 0 HU: a
#: volume with no voxel below this is not in HU (HU).
AIR_ABSENT_HU = 0.0
#: A CT holds air around the patient; with no voxel below this it is likely cropped inside
#: the body, which a person may mean (HU).
AIR_USUAL_HU = -500.0
#: A label map or mask has a handful of integer values; a CT has hundreds.
LABEL_MAP_MAX_VALUES = 64
#: Read the voxel data of a compressed NIfTI in pieces of this size to count it (bytes).
_CHUNK_BYTES = 1 << 22


def _non_finite(bad: int, voxels: int) -> str:
    return (f"{bad} of {voxels} voxels are NaN or infinite; a CT holds a number of HU in every voxel "
            "(fill the gaps with -1000 HU, air, before loading)")


def check_spacing(spacing_mm) -> tuple[list[str], list[str]]:
    spacing = [float(s) for s in spacing_mm]
    shown = " x ".join(f"{s:g}" for s in spacing)
    low, high = SPACING_REFUSED_MM
    if not all(np.isfinite(spacing)) or any(not low <= s <= high for s in spacing):
        return [f"voxel spacing {shown} mm is no CT's (a scanner gives {low:g} to {high:g} mm); "
                "check the header's units (mm, not m or um)"], []
    low, high = SPACING_USUAL_MM
    if any(not low <= s <= high for s in spacing):
        return [], [f"voxel spacing {shown} mm is unusual for a CT ({low:g} to {high:g} mm); rendering it as given"]
    return [], []


#: NIfTI datatype codes and the numpy type of their voxels.
_NIFTI_TYPES = {2: "u1", 4: "i2", 8: "i4", 16: "f4", 64: "f8", 256: "i1", 512: "u2", 768: "u4", 1024: "i8", 1280: "u8"}


@dataclass
class _NiftiScan:
    """What the bytes of a NIfTI file hold: data offset, decompressed length, and its voxels'
    non-finite count, lowest value (HU, after scl_slope/scl_inter) and first distinct values."""

    offset: int
    itemsize: int | None = None   # bytes of one stored voxel (ITK reports the rescaled type instead)
    total: int = 0
    non_finite: int = 0
    low: float = math.inf
    distinct: set[float] = field(default_factory=set)


def _nifti_layout(head: bytes) -> tuple[int, str | None, float, float] | None:
    """(voxel data offset, numpy dtype, scl_slope, scl_inter) of a NIfTI-1 or -2 header."""
    for endian in "<>":
        if len(head) >= 348 and struct.unpack(endian + "i", head[:4])[0] == 348:
            code = struct.unpack(endian + "h", head[70:72])[0]
            offset = int(struct.unpack(endian + "f", head[108:112])[0])
            slope, inter = struct.unpack(endian + "ff", head[112:120])
        elif len(head) >= 540 and struct.unpack(endian + "i", head[:4])[0] == 540:
            code = struct.unpack(endian + "h", head[12:14])[0]
            offset = int(struct.unpack(endian + "q", head[168:176])[0])
            slope, inter = struct.unpack(endian + "dd", head[176:192])
        else:
            continue
        dtype = endian + _NIFTI_TYPES[code] if code in _NIFTI_TYPES else None
        # NIfTI: a slope of 0 (or not a number) means the stored values are the values.
        if not (math.isfinite(slope) and slope != 0):
            slope, inter = 1.0, 0.0
        return offset, dtype, float(slope), float(inter) if math.isfinite(inter) else 0.0
    return None


def _scan_nifti(path: Path) -> _NiftiScan | None:
    """Read a NIfTI file's voxel bytes once, as ITK will not tell: it turns NaN voxels into 0
    (water) and pads a short file with zeros. Raises EOFError when gzip data ends early."""
    opener = gzip.open if path.name.lower().endswith(".gz") else open
    with opener(path, "rb") as f:
        head = f.read(544)
        layout = _nifti_layout(head)
        if layout is None:
            return None
        offset, dtype, slope, inter = layout
        scan = _NiftiScan(offset, np.dtype(dtype).itemsize if dtype else None, total=len(head))
        carry = head[offset:]
        if offset > len(head):  # header extensions: not voxels
            skipped = f.read(offset - len(head))
            scan.total += len(skipped)
        while chunk := f.read(_CHUNK_BYTES):
            scan.total += len(chunk)
            if dtype is None:
                continue
            carry += chunk
            whole = len(carry) - len(carry) % np.dtype(dtype).itemsize
            values = np.frombuffer(carry[:whole], dtype=dtype)
            carry = carry[whole:]
            finite = np.isfinite(values) if values.dtype.kind == "f" else None
            if finite is not None:
                scan.non_finite += int(values.size - np.count_nonzero(finite))
                values = values[finite]
            if values.size:
                scan.low = min(scan.low, float(values.min()) * slope + inter)
                if len(scan.distinct) <= LABEL_MAP_MAX_VALUES:
                    scan.distinct.update((np.unique(values).astype(np.float64) * slope + inter).tolist())
        return scan


def check_header(path: Path, hu_checked: bool = True) -> tuple[list[str], list[str]]:
    """Header-level problems of a volume file (NIfTI, MetaImage, NRRD), without loading its voxels;
    `hu_checked=False` for a file that holds no HU (a label map): its values are not judged."""
    import SimpleITK as sitk

    from .volume_io import _stderr_captured

    reader = sitk.ImageFileReader()
    reader.SetFileName(str(path))
    with _stderr_captured() as said:
        try:
            reader.ReadImageInformation()
            failed = False
        except RuntimeError:
            failed = True
    if failed:
        reason = said()[0] if said() else "unreadable header"
        return [f"cannot read this volume's header ({reason[:120]}); check the file is complete and not corrupt"], []
    if reader.GetDimension() != 3:
        return [f"a {reader.GetDimension()}D image; give each CT phase as its own 3D volume"], []
    if reader.GetNumberOfComponents() != 1:
        return [f"has {reader.GetNumberOfComponents()} components per voxel; a CT has one (HU)"], []
    errors, warnings = check_spacing(reader.GetSpacing())
    if errors or not path.name.lower().endswith((".nii", ".nii.gz")):
        return errors, warnings
    voxels = int(np.prod(reader.GetSize()))
    per_voxel = sitk.Image([1, 1, 1], reader.GetPixelID()).GetSizeOfPixelComponent()
    try:
        scanned = _scan_nifti(path)
    except (EOFError, OSError, zlib.error):
        return ["is truncated or corrupt (its compressed data ends early); copy the complete file again"], warnings
    if scanned is not None:
        offset, have = scanned.offset, scanned.total
        if scanned.non_finite:
            return [_non_finite(scanned.non_finite, voxels)], warnings
        if hu_checked and math.isfinite(scanned.low):
            found_errors, found_warnings = _hu_findings(scanned.low, np.array(sorted(scanned.distinct)))
            if found_errors:
                return found_errors, warnings
            warnings = warnings + found_warnings
        per_voxel = scanned.itemsize or per_voxel
        need = offset + voxels * per_voxel
        if have < need:
            return [f"is truncated: it holds {max(have - offset, 0) / max(per_voxel, 1):.0f} of its {voxels} voxels "
                    f"({have / need:.0%}); copy the complete file again"], warnings
    return errors, warnings


def check_hu(values: np.ndarray) -> tuple[list[str], list[str]]:
    """Voxel-level problems: non-finite values, or values that are not Hounsfield units."""
    if np.issubdtype(values.dtype, np.floating):
        bad = int(np.count_nonzero(~np.isfinite(values)))
        if bad:
            return [_non_finite(bad, values.size)], []
    if values.size == 0:
        return ["holds no voxels"], []
    return _hu_findings(float(np.min(values)), np.unique(values[:: max(1, values.size // 1_000_000)]))


def _hu_findings(low: float, distinct: np.ndarray) -> tuple[list[str], list[str]]:
    """From the lowest value and (some of) the distinct values: is this a CT in HU?"""
    if low >= AIR_ABSENT_HU:
        if distinct.size <= LABEL_MAP_MAX_VALUES and np.all(distinct == np.rint(distinct)):
            return [f"holds only {distinct.size} distinct values from {distinct.min():g} to {distinct.max():g}: a label "
                    "map or mask, not a CT in HU; give the CT image itself"], []
        return [f"has no voxel below {low:g} HU, yet air is -1000 HU: it is not in HU (stored without its rescale "
                "intercept, offset by +1024 or +2048?); convert it to HU first"], []
    if low > AIR_USUAL_HU:
        return [], [f"has no air (lowest voxel {low:g} HU, air is -1000 HU): cropped inside the body? rendering it as given"]
    return [], []
