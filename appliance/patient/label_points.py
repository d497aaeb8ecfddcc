"""Named points of a CT from its label map: the centroid of a label, in the `ct` frame (LPS mm).

A label map is an integer volume on the CT's own grid (same voxels, origin, spacing and
direction), each voxel holding the id of the structure it belongs to (0 = none), as
segmentation tools write it (3D Slicer, ITK-SNAP, TotalSegmentator). Ids get names from:

- a case profile's `respiration.labels` (the roles lungs, liver, spine, ribs, diaphragm,
  each a list of ids) when the label map is given through that profile;
- a label table: one label a line, its id first, then its name (a 3D Slicer colour table,
  `1 liver 221 130 101 255`), or a quoted name last (an ITK-SNAP label description,
  `1 255 0 0 1 1 1 "left lung"`); `#` starts a comment;
- always `label-N` for every id N present.

The centroid is the mean of the label's voxel centres taken through `T_ct_from_voxel`, which is
linear, so it is the centroid of the structure as the CT samples it. It may lie outside a
structure that is not convex (both lungs together, the ribs): it is a place to centre the
field on, not a point of the organ.
"""

from __future__ import annotations

import re
import shlex
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import FluorosimError
from ..geometry import apply
from .volume import Volume

#: A label map's voxels may sit this far from the CT's and still count as the same grid (mm):
#: float32 headers (NIfTI) round origins near 500 mm at about 3e-5 mm.
GRID_TOLERANCE_MM = 1e-3
LABEL_PREFIX = "label-"


def label_map_on_grid(path: Path, ct: Volume) -> np.ndarray:
    """The label ids at `path` as an int16 array shaped like `ct.hu`, or a one-line refusal
    when the file is not on the CT's grid."""
    from .volume_io import load_volume

    # A folder is a label map exported as an image series (one slice a file, the ids as pixel
    # values), read as the CT's series is: sorted by position, gaps and mixed series refused.
    lab = load_volume(path, hu_checked=False)   # a label map holds label ids, not HU
    if lab.hu.shape != ct.hu.shape or not np.allclose(lab.T_ct_from_voxel, ct.T_ct_from_voxel, atol=GRID_TOLERANCE_MM):
        raise FluorosimError(f"{path}: label map is not on the CT's grid ({lab.shape_xyz} voxels vs the CT's "
                             f"{ct.shape_xyz}, or another origin/spacing); resample it onto the CT")
    return np.asarray(lab.hu)


def read_label_table(path: Path) -> dict[str, list[int]]:
    """Names (lower case) to ids from a label table; a bad line is refused as FILE:LINE."""
    try:
        text = path.read_text(encoding="utf-8", errors="strict")
    except FileNotFoundError:
        raise FluorosimError(f"{path}: no such label table; give a text file of `ID NAME` lines") from None
    except (OSError, UnicodeDecodeError) as e:
        raise FluorosimError(f"{path}: cannot read the label table ({getattr(e, 'strerror', None) or e}); "
                             f"give a UTF-8 text file of `ID NAME` lines") from None
    names: dict[str, list[int]] = {}
    for number, line in enumerate(text.splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        quoted = re.search(r'"([^"]*)"\s*$', line)
        try:
            fields = shlex.split(line) if quoted else line.split()
            label = int(fields[0])
        except (ValueError, IndexError):
            raise FluorosimError(f"{path}:{number}: {line[:60]!r}: a line is an integer id, then the label's name") from None
        name = (quoted.group(1) if quoted else (fields[1] if len(fields) > 1 else "")).strip().lower()
        if not name:
            raise FluorosimError(f"{path}:{number}: label {label} has no name; write `{label} NAME`")
        if label != 0:          # 0 is the background, not a structure
            names.setdefault(name, []).append(label)
    return names


@dataclass(frozen=True)
class LabelPoints:
    """A label map on a CT's grid and the names of its labels."""

    labels: np.ndarray             # int16 ids, shaped like the CT's hu
    T_ct_from_voxel: np.ndarray
    source: str                    # the file, for messages
    named: dict[str, list[int]]    # lower-case name -> ids (roles or a table), without the label-N names

    def ids_present(self) -> list[int]:
        return [int(v) for v in np.unique(self.labels) if v != 0]

    def names(self) -> list[str]:
        return list(self.named) + [f"{LABEL_PREFIX}{i}" for i in self.ids_present()]

    def ids(self, name: str) -> list[int]:
        key = name.strip().lower()
        if key in self.named:
            return self.named[key]
        if key.startswith(LABEL_PREFIX) and key[len(LABEL_PREFIX):].isdigit():
            label = int(key[len(LABEL_PREFIX):])
            if label in self.ids_present():
                return [label]
        raise FluorosimError(f"--target {name!r}: no label of that name in {self.source}; "
                             f"the names there are: {', '.join(self.names()) or 'none (the map holds only 0)'}")

    def centroid(self, name: str) -> tuple[np.ndarray, int]:
        """The label's centroid (LPS mm) and its voxel count."""
        ids = self.ids(name)
        mask = np.isin(self.labels, np.asarray(ids, dtype=self.labels.dtype))
        count = int(mask.sum())
        if count == 0:
            raise FluorosimError(f"--target {name!r}: label {', '.join(map(str, ids))} has no voxels in {self.source}; "
                                 f"the names there are: {', '.join(self.names())}")
        # Mean index along each axis from the per-slab counts: no index arrays of the whole grid.
        k = float(mask.sum(axis=(1, 2)) @ np.arange(mask.shape[0])) / count
        j = float(mask.sum(axis=(0, 2)) @ np.arange(mask.shape[1])) / count
        i = float(mask.sum(axis=(0, 1)) @ np.arange(mask.shape[2])) / count
        return apply(self.T_ct_from_voxel, np.array([i, j, k])), count


def label_points(given: Path, ct: Volume, table: Path | None = None) -> LabelPoints:
    """The label map `given` (a volume file, or a case profile whose `respiration.label_map`
    and `respiration.labels` name it) with the names of its labels."""
    named: dict[str, list[int]] = {}
    if given.suffix.lower() in (".yaml", ".yml"):
        from ..config.case import CaseProfile
        from ..config.loading import load_profile, resolve

        case = load_profile(given, CaseProfile)
        breathing = case.respiration
        if breathing is None or not breathing.label_map:
            raise FluorosimError(f"{given}: respiration.label_map: the case names no label map; give the label map "
                                 f"file itself with --labels")
        path = resolve(given, breathing.label_map)
        named = {role: list(ids) for role, ids in (breathing.labels or {}).items() if ids}
    else:
        path = given
    if table is not None:
        for name, ids in read_label_table(table).items():
            named.setdefault(name, ids)
    return LabelPoints(label_map_on_grid(path, ct), ct.T_ct_from_voxel, str(path), named)
