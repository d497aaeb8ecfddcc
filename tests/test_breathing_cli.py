"""`fluorosim render --phase-time T --respiration ...` of a breathing case: the contract external checks use."""


import numpy as np
import pytest
import SimpleITK as sitk
import synthetic_chest as sc
from in_process_cli import fluorosim as in_process
from test_breathing_motion import SOD, T_XRAY_FROM_CT, dome_edge_row
from test_xray_cli import small_profile

from appliance.cli import main


def write_image(array, T, path):
    img = sitk.GetImageFromArray(array)
    img.SetSpacing([float(s) for s in np.linalg.norm(T[:3, :3], axis=0)])
    img.SetOrigin([float(o) for o in T[:3, 3]])
    sitk.WriteImage(img, str(path), True)


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    d = tmp_path_factory.mktemp("breathing")
    small_profile(d)
    ct = sc.chest()
    write_image(ct.hu, ct.T_ct_from_voxel, d / "chest.mha")
    write_image(sc.chest_labels(), ct.T_ct_from_voxel, d / "chest-labels.mha")
    (d / "case.yaml").write_text(
        "title: Synthetic chest\nphases:\n  - {volume: chest.mha, time_s: 0}\n"
        "respiration:\n  diaphragm_mm: 15\n  rib_gamma_deg: 2\n  rib_lambda_deg: 3\n  rate_per_min: 15\n"
        "  label_map: chest-labels.mha\n  labels: {lungs: [10, 11], spine: [30], ribs: []}\n")
    (d / "pose.yaml").write_text("T_xray_from_ct:\n" + "".join(f"  - [{', '.join(f'{x:.12g}' for x in row)}]\n"
                                                             for row in T_XRAY_FROM_CT))
    return d


def render(d, t, out, *extra):
    r = in_process("render", "--volume", "case.yaml", "--fluoroscope", "flat256.yaml", "--pose", "pose.yaml",
                  "--quantity", "line-integral", "--output", out, "--phase-time", t, *extra, cwd=d)
    assert r.returncode == 0, r.stderr
    return np.load(d / out)


def test_dome_moves_by_the_amplitude_between_end_expiration_and_end_inspiration(case):
    # rate 15/min: f = 0.25 Hz, end-inspiration at 1/(4f) = 1 s, end-expiration at 3/(4f) = 3 s (and + k/f).
    exp, ins = render(case, 3.0, "exp.npy"), render(case, 5.0, "ins.npy")
    # Half the amplitude at twice the rate: end-inspiration at 1/(4f) = 0.5 s.
    half = render(case, 0.5, "half.npy", "--respiration", "diaphragm_mm=7.5,rate_per_min=30")
    fx, fy, cx, cy = 929.054, 929.054, 127.5, 127.5
    column = int(round(cx + fx * -50.0 / SOD))
    r_apex = int(round(cy - fy * sc.DOME_APEX_Z / SOD))
    level = 0.5 * (exp[r_apex - 8, column] + exp[r_apex + 8, column])
    rows = [dome_edge_row(img, column, level, r_apex - 12) for img in (exp, ins, half)]
    assert rows[1] - rows[0] == pytest.approx(fy * 15.0 / SOD, rel=0.1)
    assert (rows[2] - rows[0]) / (rows[1] - rows[0]) == pytest.approx(0.5, rel=0.1)


@pytest.mark.parametrize("value, expect", [
    ("diaphragm=3", "unknown key 'diaphragm'"),
    ("rate_per_min=fast", "respiration.rate_per_min"),
])
def test_bad_overrides_are_one_line_errors(case, value, expect, capfd, monkeypatch):
    # The command in this process; capfd reads file descriptors 1 and 2, so a warning from a C
    # library (SimpleITK, PoCL) would be counted as a second line just as from a child process.
    monkeypatch.chdir(case)
    code = main(["render", "--volume", "case.yaml", "--fluoroscope", "flat256.yaml", "--pose", "pose.yaml",
                 "--quantity", "line-integral", "--output", "x.npy", "--phase-time", "1", "--respiration", value])
    stderr = capfd.readouterr().err
    assert code != 0 and expect in stderr and "Traceback" not in stderr
    assert len(stderr.strip().splitlines()) == 1, stderr


@pytest.mark.parametrize("value, expect", [
    ("diaphragm_mm", "is not KEY=VALUE"),
    ("diaphragm_mm=1,diaphragm_mm=2", "given twice"),
    ("labels=3", "unknown key 'labels'"),
])
def test_override_syntax(value, expect):
    from appliance.errors import FluorosimError
    from appliance.patient.breathing_case import parse_overrides
    with pytest.raises(FluorosimError, match=expect):
        parse_overrides(value)


def test_overrides_are_validated_against_the_section():
    from appliance.config.case import CaseProfile
    from appliance.errors import FluorosimError
    from appliance.patient.breathing_case import parse_overrides, respiration_for
    case = CaseProfile(title="t", phases=[{"volume": "ct.mha", "time_s": 0}], respiration={"diaphragm_mm": 12})
    p = respiration_for(case, parse_overrides("rate_per_min=20, rib_gamma_deg=4"), "case.yaml")
    assert (p.diaphragm_mm, p.rate_per_min, p.rib_gamma_deg) == (12, 20, 4)
    with pytest.raises(FluorosimError, match=r"case.yaml: respiration.diaphragm_mm: .*-3"):
        respiration_for(case, parse_overrides("diaphragm_mm=-3"), "case.yaml")
    with pytest.raises(FluorosimError, match="rate_max_per_min"):
        respiration_for(case, parse_overrides("rate_per_min=50"), "case.yaml")
    plain = CaseProfile(title="t", phases=[{"volume": "ct.mha", "time_s": 0}])
    assert respiration_for(plain, {}, "case.yaml") is None


def test_4d_ct_render_time_follows_the_breathing_rate(tmp_path):
    """A 4-phase CT (one 4 s breath, end-expiration at 2 s) at 30 breaths/min: end-inspiration
    (t = 1/(4f) = 0.5 s) shows the phase half a cycle from end-expiration, 0 s."""
    from appliance.xray.commands import _volume_and_case
    from appliance.xray.truth.analytic import box_volume

    for k in range(4):
        vol = box_volume((8, 8, 8), (2.0, 2.0, 2.0), (2, 2, 2), (5, 5, 5), hu=100 * k)[0]
        write_image(vol.hu, vol.T_ct_from_voxel, tmp_path / f"p{k}.mha")
    (tmp_path / "4d.yaml").write_text(
        "title: 4D\nphases:\n" + "".join(f"  - {{volume: p{k}.mha, time_s: {k}}}\n" for k in range(4))
        + "respiration: {rate_per_min: 30, ct_end_expiration_s: 2}\n")
    for t, expect_hu in ((1.5, 200), (0.5, 0), (1.0, 100), (2.5, 0)):
        vol, _, _ = _volume_and_case(tmp_path / "4d.yaml", t)
        assert vol.hu.max() == expect_hu, t
