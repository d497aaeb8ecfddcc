"""`fluorosim render`: the command-line contract, run through the command's own main (see in_process_cli)."""

from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk
from in_process_cli import fluorosim as in_process

from appliance.config.fluoroscope import FluoroscopeProfile
from appliance.config.loading import load_profile
from appliance.geometry import make_transform, rotation_about
from appliance.xray.truth.analytic import box_chords, box_volume, pixel_rays_ct

ROOT = Path(__file__).resolve().parents[1]
PROFILE = ROOT / "configs" / "fluoroscopes" / "generic-flat-detector.yaml"


def small_profile(d):
    """The flat-panel room read out at 256 x 256 (pitch and intrinsics scaled), to keep the test quick."""
    text = PROFILE.read_text()
    for old, new in (("columns: 1024", "columns: 256"), ("rows: 1024", "rows: 256"),
                     ("pixel_pitch_mm: 0.296", "pixel_pitch_mm: 1.184"), ("fx: 3716.216", "fx: 929.054"),
                     ("fy: 3716.216", "fy: 929.054"), ("cx: 511.5", "cx: 127.5"), ("cy: 511.5", "cy: 127.5")):
        assert old in text
        text = text.replace(old, new)
    (d / "flat256.yaml").write_text(text)
    return d / "flat256.yaml"


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    d = tmp_path_factory.mktemp("render")
    small_profile(d)
    vol, lo, hi = box_volume((20, 24, 24), (5.0, 5.0, 5.0), (4, 6, 3), (19, 17, 16), hu=0)
    img = sitk.GetImageFromArray(vol.hu)
    img.SetSpacing((5.0, 5.0, 5.0))
    img.SetOrigin(tuple(vol.T_ct_from_voxel[:3, 3]))
    sitk.WriteImage(img, str(d / "box.nii.gz"))
    T = make_transform(rotation_about([0.2, 1.0, 0.0], 0.4), [3.0, -2.0, 750.0])
    (d / "pose.yaml").write_text("T_xray_from_ct:\n" + "".join(f"  - [{', '.join(f'{x:.12g}' for x in row)}]\n" for row in T))
    return d, lo, hi, T


def test_line_integral_npy_matches_closed_form(case):
    d, lo, hi, T = case
    r = in_process("render", "--volume", "box.nii.gz", "--fluoroscope", "flat256.yaml", "--pose", "pose.yaml",
                  "--quantity", "line-integral", "--output", "li.npy", cwd=d)
    assert r.returncode == 0, r.stderr
    mu = float(r.stdout.split("mu_water = ")[1].split()[0])
    img = np.load(d / "li.npy")
    f = load_profile(d / "flat256.yaml", FluoroscopeProfile)
    assert img.shape == (f.detector.rows, f.detector.columns) and img.dtype == np.float32
    s, dirs = pixel_rays_ct(f.intrinsics.K(), T, f.detector.rows, f.detector.columns)
    truth = box_chords(s, dirs, lo, hi) * mu
    sel = truth > 10 * mu
    rel = np.abs(img[sel] - truth[sel]) / truth[sel]
    assert sel.sum() > 500 and rel.max() < 0.005 and rel.mean() < 0.001


def test_display_png_and_zoom(case):
    d, _, _, _ = case
    r = in_process("render", "--volume", "box.nii.gz", "--fluoroscope", "flat256.yaml", "--pose", "pose.yaml",
                  "--quantity", "display", "--output", "d.png", "--zoom", "2", "--seed", "1", cwd=d)
    assert r.returncode == 0, r.stderr
    import cv2
    img = cv2.imread(str(d / "d.png"), cv2.IMREAD_UNCHANGED)
    assert img.shape == (256, 256) and img.dtype == np.uint8 and img.max() > 0


@pytest.mark.parametrize("change, expect", [
    ({"pose": "bad_pose.yaml"}, "not a rigid transform"),
    ({"volume": "missing.nii"}, "no such file"),
    ({"volume": "junk.mha"}, "cannot read"),
    ({"output": "nowhere/out.npy"}, "does not exist"),
    ({"fluoroscope": "bad_profile.yaml"}, "bad_profile.yaml"),
])
def test_bad_input_exits_2_with_one_line(case, change, expect):
    d, _, _, T = case
    (d / "bad_pose.yaml").write_text("T_xray_from_ct:\n" + "".join(f"  - [{', '.join(str(2 * x) for x in row)}]\n" for row in T))
    (d / "junk.mha").write_text("ObjectType = Image\nNDims = 3\n")
    # The tube's kV, not the curve's 70 kV point.
    (d / "bad_profile.yaml").write_text((d / "flat256.yaml").read_text().replace("kvp: 70\n", "kvp: 7000\n", 1))
    args = {"volume": "box.nii.gz", "fluoroscope": "flat256.yaml", "pose": "pose.yaml", "output": "o.npy"}
    args.update(change)
    # In the test process: a traceback would fail the test as surely as on stderr; the real
    # process's stderr is checked by test_breathing_cli's bad overrides.
    r = in_process("render", "--volume", args["volume"], "--fluoroscope", args["fluoroscope"], "--pose", args["pose"],
                  "--quantity", "line-integral", "--output", args["output"], cwd=d)
    assert r.returncode == 2
    assert expect in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert "Traceback" not in r.stderr


def test_phase_time_picks_the_phase_of_a_case(tmp_path):
    from appliance.errors import FluorosimError
    from appliance.xray.commands import _volume_and_case

    for i, hu in enumerate((0, 500)):
        vol, _, _ = box_volume((6, 6, 6), (2.0, 2.0, 2.0), (1, 1, 1), (4, 4, 4), hu=hu)
        sitk.WriteImage(sitk.GetImageFromArray(vol.hu), str(tmp_path / f"phase{i}.mha"))
    (tmp_path / "case.yaml").write_text(
        "title: two phases\nphases:\n  - {volume: phase0.mha, time_s: 0.0}\n  - {volume: phase1.mha, time_s: 1.0}\n"
        "materials: {bone_min_hu: 300}\n")
    for t, hu in ((0.2, 0), (1.5, 500), (2.2, 0), (3.1, 500)):      # loops with a 2 s cycle
        vol, materials, contrast = _volume_and_case(tmp_path / "case.yaml", t)
        assert vol.hu.max() == hu, t
        assert materials.bone_min_hu == 300 and contrast is None
    with pytest.raises(FluorosimError, match="phase-time"):
        _volume_and_case(tmp_path / "phase0.mha", 1.0)


def test_render_and_bench_are_registered():
    from appliance.cli import build_parser

    args = build_parser().parse_args(["bench", "drr", "--skip", "speed,memory", "--frames", "3"])
    assert args.frames == 3 and callable(args.run)
    args = build_parser().parse_args(["render", "--volume", "v.nii", "--fluoroscope", "f.yaml", "--pose", "p.yaml",
                                      "--quantity", "intensity", "--output", "o.npy", "--zoom", "4", "--phase-time", "1.5"])
    assert (args.zoom, args.phase_time, args.quantity) == (4, 1.5, "intensity")


def test_size_renders_the_same_field_on_another_matrix(case):
    d, lo, hi, T = case
    r = in_process("render", "--volume", "box.nii.gz", "--fluoroscope", "flat256.yaml", "--pose", "pose.yaml",
                  "--quantity", "line-integral", "--output", "small.npy", "--size", "96x64", cwd=d)
    assert r.returncode == 0, r.stderr
    assert "casting 96 x 64 rays" in r.stdout and "preparing 24 x 24 x 20 voxels" in r.stdout
    mu = float(r.stdout.split("mu_water = ")[1].split()[0])
    img = np.load(d / "small.npy")
    assert img.shape == (64, 96)
    # The 256 x 256 field read out at 96 x 64: pixels 256/96 and 256/64 times as big, edges kept.
    f = load_profile(d / "flat256.yaml", FluoroscopeProfile)
    sx, sy = 96 / 256, 64 / 256
    K = np.array([[f.intrinsics.fx * sx, 0, (f.intrinsics.cx + 0.5) * sx - 0.5],
                  [0, f.intrinsics.fy * sy, (f.intrinsics.cy + 0.5) * sy - 0.5], [0, 0, 1]])
    s, dirs = pixel_rays_ct(K, T, 64, 96)
    truth = box_chords(s, dirs, lo, hi) * mu
    sel = truth > 10 * mu
    assert sel.sum() > 100 and (np.abs(img[sel] - truth[sel]) / truth[sel]).max() < 0.005
    bad = in_process("render", "--volume", "box.nii.gz", "--fluoroscope", "flat256.yaml", "--pose", "pose.yaml",
                    "--quantity", "line-integral", "--output", "x.npy", "--size", "0", cwd=d)
    assert bad.returncode == 2 and "16 to 8192" in bad.stderr


def test_render_help_defines_the_xray_frame_of_the_pose_file(case):
    d, _, _, _ = case
    r = in_process("render", "--help", cwd=d)
    text = " ".join(r.stdout.split())
    assert "focal spot at the origin" in text and "+z along the principal ray toward the detector" in text
    assert "LPS" in text
