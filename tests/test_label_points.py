"""`fluorosim case place --target NAME --labels FILE`: a label's centroid, known by construction,
placed at the isocentre and imaged at the centre of the detector; names from a label table,
from a case profile's respiration roles, and one-line refusals."""

from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk
from test_case_placement import shadows

from appliance.cli import main
from appliance.config.fluoroscope import FluoroscopeProfile
from appliance.config.loading import load_profile

CONFIGS = Path(__file__).resolve().parents[1] / "configs"

SPACING_MM = 2.0
N = 64
DIRECTION = np.diag([-1.0, -1.0, 1.0])          # stored RAS-wise, as NIfTI exports are
ORIGIN = np.array([71.0, 40.0, -260.0])         # LPS mm of voxel (0, 0, 0)
# Two blocks of label 3 in index space (i, j, k slices): 10 x 8 x 8 = 640 voxels centred at
# i = 14.5 and 6 x 8 x 8 = 384 voxels centred at i = 42.5, so their centroid is at
# i = (640 * 14.5 + 384 * 42.5) / 1024 = 25, j = 31.5, k = 33.5.
BLOCKS = ((slice(10, 20), slice(28, 36), slice(30, 38)), (slice(40, 46), slice(28, 36), slice(30, 38)))
CENTROID_IJK = np.array([25.0, 31.5, 33.5])
CENTROID_LPS = ORIGIN + DIRECTION @ (SPACING_MM * CENTROID_IJK)
OTHER_BLOCK = (slice(5, 9), slice(5, 9), slice(5, 9))   # label 7, far from the centroid


def write(path: Path, array_kji: np.ndarray) -> None:
    image = sitk.GetImageFromArray(array_kji)
    image.SetSpacing((SPACING_MM,) * 3)
    image.SetOrigin(tuple(ORIGIN))
    image.SetDirection(tuple(DIRECTION.reshape(-1)))
    sitk.WriteImage(image, str(path))


@pytest.fixture(scope="module")
def ct_and_labels(tmp_path_factory):
    """Air with one steel-dense ball at the label's centroid (where no label voxel is), and the
    label map: label 3 as the two blocks, label 7 as a small cube."""
    folder = tmp_path_factory.mktemp("labelled")
    k, j, i = np.mgrid[0:N, 0:N, 0:N]
    lps = np.stack([i, j, k], -1) * SPACING_MM @ DIRECTION.T + ORIGIN
    hu = np.full((N, N, N), -1000, np.int16)
    hu[np.linalg.norm(lps - CENTROID_LPS, axis=-1) <= 5.0] = 3000
    labels = np.zeros((N, N, N), np.uint8)
    for i_, j_, k_ in BLOCKS:
        labels[k_, j_, i_] = 3
    labels[OTHER_BLOCK[2], OTHER_BLOCK[1], OTHER_BLOCK[0]] = 7
    assert labels[int(CENTROID_IJK[2]), int(CENTROID_IJK[1]), int(CENTROID_IJK[0])] == 0
    write(folder / "ct.nii.gz", hu)
    write(folder / "labels.nii.gz", labels)
    (folder / "names.txt").write_text("# 3D Slicer colour table\n0 Background 0 0 0 0\n3 liver 221 130 101 255\n"
                                      "7 left_kidney 185 102 83 255\n")
    return folder


def test_a_named_label_centroid_images_at_the_detector_centre(ct_and_labels, tmp_path, capsys):
    out = tmp_path / "named.yaml"
    assert main(["case", "place", str(ct_and_labels / "ct.nii.gz"), "--target", "Liver",
                 "--labels", str(ct_and_labels / "labels.nii.gz"), "--label-names", str(ct_and_labels / "names.txt"),
                 "--out", str(out)]) == 0
    said = capsys.readouterr().out
    assert "centroid of label 'Liver', 1024 voxels of labels.nii.gz" in said
    assert "LPS (" + ", ".join(f"{v:g}" for v in CENTROID_LPS) + ") mm" in said
    assert main(["validate", str(out)]) == 0
    fluoroscope = load_profile(CONFIGS / "fluoroscopes" / "generic-ii-carm.yaml", FluoroscopeProfile)
    uv, centre = shadows(fluoroscope, out)
    assert len(uv) == 1                                  # the ball alone: the labels are not in the CT
    assert np.linalg.norm(uv[0] - centre) < 0.3


def test_label_n_needs_no_table_and_an_itk_snap_description_names_ids(ct_and_labels, tmp_path, capsys):
    ct, labels = str(ct_and_labels / "ct.nii.gz"), str(ct_and_labels / "labels.nii.gz")
    assert main(["case", "place", ct, "--target", "label-7", "--labels", labels]) == 0
    # Label 7 fills i, j, k = 5..8: its centroid is index (6.5, 6.5, 6.5).
    expected = ORIGIN + DIRECTION @ np.full(3, SPACING_MM * 6.5)
    assert "target (" + ", ".join(f"{v:g}" for v in expected) + ") mm" in capsys.readouterr().out
    snap = ct_and_labels / "snap.txt"
    snap.write_text('################################################\n'
                    '# ITK-SnAP Label Description File\n'
                    '    0     0    0    0        0  0  0    "Clear Label"\n'
                    '    7   255    0    0        1  1  1    "Left kidney"\n')
    assert main(["case", "place", ct, "--target", "left kidney", "--labels", labels, "--label-names", str(snap)]) == 0
    assert "target (" + ", ".join(f"{v:g}" for v in expected) + ") mm" in capsys.readouterr().out


def test_roles_of_a_case_profile_name_the_labels(ct_and_labels, tmp_path, capsys):
    case = ct_and_labels / "breathing.yaml"
    case.write_text("title: labelled\nphases:\n  - volume: ct.nii.gz\n    time_s: 0\nat_end: hold\n"
                    "respiration:\n  label_map: labels.nii.gz\n  labels:\n    liver: [3]\n    spine: [7]\n")
    assert main(["case", "place", str(ct_and_labels / "ct.nii.gz"), "--target", "liver", "--labels", str(case)]) == 0
    assert "target (" + ", ".join(f"{v:g}" for v in CENTROID_LPS) + ") mm" in capsys.readouterr().out


def test_an_unknown_name_is_one_line_listing_the_names(ct_and_labels, tmp_path, capsys):
    assert main(["case", "place", str(ct_and_labels / "ct.nii.gz"), "--target", "spleen",
                 "--labels", str(ct_and_labels / "labels.nii.gz"), "--label-names", str(ct_and_labels / "names.txt"),
                 "--out", str(tmp_path / "x.yaml")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert "'spleen'" in err[0] and "liver, left_kidney, label-3, label-7" in err[0]
    assert not (tmp_path / "x.yaml").exists()


def test_refusals_of_bad_label_input(ct_and_labels, tmp_path, capsys):
    ct, labels = str(ct_and_labels / "ct.nii.gz"), str(ct_and_labels / "labels.nii.gz")
    # A name without a label map.
    assert main(["case", "place", ct, "--target", "liver"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "three numbers" in err[0] and "--labels FILE" in err[0]
    # A table line without an id, named by file and line.
    bad = tmp_path / "bad.txt"
    bad.write_text("3 liver\nkidney 7\n")
    assert main(["case", "place", ct, "--target", "liver", "--labels", labels, "--label-names", str(bad)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{bad}:2:" in err[0]
    # A label map on another grid.
    small = tmp_path / "small.nii.gz"
    sitk.WriteImage(sitk.GetImageFromArray(np.zeros((8, 8, 8), np.uint8)), str(small))
    assert main(["case", "place", ct, "--target", "label-1", "--labels", str(small)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not on the CT's grid" in err[0]
    # A name in the table whose id has no voxels.
    empty = tmp_path / "empty.txt"
    empty.write_text("9 spleen\n")
    assert main(["case", "place", ct, "--target", "spleen", "--labels", labels, "--label-names", str(empty)]) == 2
    assert "no voxels" in capsys.readouterr().err
    # Numbers still win over names when a label map is given.
    point = ",".join(f"{v:g}" for v in CENTROID_LPS)
    assert main(["case", "place", ct, "--target=" + point, "--labels", labels]) == 0


def test_a_label_map_exported_as_a_dicom_series(tmp_path, capsys):
    """CT and label map as two DICOM image series on the same slices, as a PACS or a segmentation
    tool exports them: the label's centroid comes from the series' own geometry."""
    from test_volume_io import write_series

    # Slices at z = 100 + 2.5 k mm, first pixel at x -50, y -40 mm, columns 0.8 mm, rows 0.9 mm apart
    # (write_series' geometry, typed here from its header values).
    nz, ny, nx = 12, 20, 24
    hu = np.full((nz, ny, nx), -1000, np.int16)
    hu[:, 5:15, 4:20] = 0                              # a water block, so the CT is a CT in HU
    labels = np.zeros((nz, ny, nx), np.int16)
    labels[2:4, 6:10, 8:12] = 5                        # 2 x 4 x 4 voxels centred at k 2.5, j 7.5, i 9.5
    labels[8:10, 6:10, 8:12] = 5                       # and at k 8.5: together centred at k 5.5
    write_series(tmp_path / "ct", hu)
    write_series(tmp_path / "labels", labels, intercept=0.0)
    expected = (-50.0 + 0.8 * 9.5, -40.0 + 0.9 * 7.5, 100.0 + 2.5 * 5.5)
    out = tmp_path / "placed.yaml"
    assert main(["case", "place", str(tmp_path / "ct"), "--target", "label-5", "--labels", str(tmp_path / "labels"),
                 "--out", str(out)]) == 0
    said = capsys.readouterr().out
    assert "64 voxels of labels" in said and "LPS (" + ", ".join(f"{v:g}" for v in expected) + ") mm" in said
    assert main(["validate", str(out)]) == 0
    # A label series missing a slice is refused as the CT's would be, in one line.
    sorted((tmp_path / "labels").iterdir())[0].unlink()
    capsys.readouterr()
    assert main(["case", "place", str(tmp_path / "ct"), "--target", "label-5", "--labels", str(tmp_path / "labels")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(tmp_path / "labels") in err[0]
