"""`fluorosim validate` sees a label map or an offset CT in MetaImage, NRRD and DICOM volumes,
from a few slices, as FILE:LINE: FIELD: MESSAGE (a NIfTI's are seen by its byte scan, see
test_bad_input); a healthy CT passes, and one whose sampled slices lack air but whose end
slices hold it is not refused on the sample's word."""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk
from test_bad_input import configs, ct_like, one_problem, refused  # noqa: F401  # configs: the fixture
from test_volume_io import write_series

from appliance.cli import main


def write_file(path, arr, compressed=False):
    image = sitk.GetImageFromArray(arr)
    image.SetSpacing((0.8, 0.8, 2.0))
    sitk.WriteImage(image, str(path), useCompression=compressed)
    return path.name


def stored_without_intercept():
    """A CT as a scanner stores it, air at -1024 HU and below clipped, shifted by +1024: all >= 0."""
    return (np.clip(ct_like(), -1024, None) + 1024).astype(np.int16)


def label_map(shape=(12, 14, 16)):
    ct = ct_like(shape)
    return ((ct > -500).astype(np.int16) + (ct > 500)).astype(np.int16)


def truncated(path, arr):
    """A MetaImage whose voxel file was cut to half its length (a copy that stopped early)."""
    name = write_file(path, arr)
    raw = path.with_suffix(".raw")
    raw.write_bytes(raw.read_bytes()[: raw.stat().st_size // 2])
    return name


VOLUMES = {
    "truncated-mhd-raw": (lambda d: truncated(d / "v.mhd", ct_like()), "check the file is complete"),
    "label-map-mha": (lambda d: write_file(d / "v.mha", label_map().astype(np.uint8)), "label map or mask"),
    "offset-mha-compressed": (lambda d: write_file(d / "v.mha", (ct_like() + 2048).astype(np.int16), compressed=True),
                              "rescale intercept"),
    "label-map-nrrd": (lambda d: write_file(d / "v.nrrd", label_map(), compressed=True), "label map or mask"),
    "offset-mhd-raw": (lambda d: write_file(d / "v.mhd", stored_without_intercept()), "rescale intercept"),
    # Stored HU + 1024 with an intercept of 0: the exporter dropped the rescale.
    "offset-dicom": (lambda d: write_series(d / "series", stored_without_intercept(), intercept=0.0) or "series",
                     "rescale intercept"),
    "label-map-dicom": (lambda d: write_series(d / "series", label_map(), intercept=0.0) or "series", "label map or mask"),
}


def case_naming(configs, volume: str):  # noqa: F811
    case = configs / "cases/own.yaml"
    case.write_text(f"title: own CT\nphases:\n  - volume: {volume}\n    time_s: 0\n")
    return case


@pytest.mark.parametrize("name", VOLUMES)
def test_validate_refuses_what_is_no_ct_in_hu(configs, capsys, name):  # noqa: F811
    make, expected = VOLUMES[name]
    case = case_naming(configs, make(configs / "cases"))
    problem = one_problem(refused(["validate", str(case)], capsys))
    assert problem.startswith(f"{case}:3: phases[0].volume: ") and expected in problem


@pytest.mark.parametrize("kind", ["mha", "nrrd", "dicom"])
def test_validate_passes_a_ct_and_reads_the_whole_before_refusing(configs, capsys, kind):  # noqa: F811
    hu = ct_like((12, 14, 16))
    # No air in the inner slices (a body cropped tight), air only in the first and last, which a
    # sample of inner slices misses: the sample's doubt is settled by the whole volume.
    hu[1:-1] = np.clip(hu[1:-1], -200, None)
    arr = hu.astype(np.int16)
    folder = configs / "cases"
    volume = write_series(folder / "series", arr) or "series" if kind == "dicom" else write_file(folder / f"v.{kind}", arr)
    case = case_naming(configs, volume)
    assert main(["validate", str(case)]) == 0
    out = capsys.readouterr()
    assert "warning" not in out.err + out.out and "problem" not in out.err
