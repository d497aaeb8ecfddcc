"""Bad input is refused where it enters: one line naming the file and field with the physical
or legal bound, exit 2, no traceback, in bounded time, and nothing already recorded lost.

The bounds asserted are the regulation's and the hardware's (21 CFR 1020.32: 88 mGy/min,
176 with high-level control, a 5-minute alarm), typed here from their sources, not read back
from the code under test.
"""

from __future__ import annotations

import hashlib
import json
import logging
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk

from appliance.cli import main
from appliance.errors import FluorosimError
from appliance.tracking.trajectory import load_trajectory
from drivers.scripted_input import ScriptedInput, ScriptProblem

REPO = Path(__file__).resolve().parents[1]
CONFIGS = REPO / "configs"
#: A refusal is a check, not a computation: it comes within this (s, on a shared two-core machine).
QUICK_S = 10.0


@pytest.fixture
def configs(tmp_path):
    """A copy of the shipped configs/ tree to break."""
    root = tmp_path / "configs"
    shutil.copytree(CONFIGS, root)
    return root


def edit(path: Path, old: str, new: str) -> None:
    text = path.read_text()
    assert old in text, f"test setup: {old!r} not in {path.name}"
    path.write_text(text.replace(old, new, 1))


def line_of(path: Path, anchor: str) -> int:
    return next(i for i, l in enumerate(path.read_text().splitlines(), start=1) if anchor in l)


def refused(argv: list[str], capsys) -> list[str]:
    """Run a command as a person would; assert exit 2, quickly, without a traceback; its stderr lines."""
    start = time.monotonic()
    rc = main(argv)
    took = time.monotonic() - start
    err = capsys.readouterr().err
    assert rc == 2, err
    assert took < QUICK_S
    assert "Traceback" not in err
    return [l for l in err.splitlines() if l.strip()]


def one_problem(lines: list[str]) -> str:
    """The single problem `validate` reports (its last line counts the problems)."""
    problems = [l for l in lines if not l.endswith("problem(s) found") and not l.startswith("warning:")]
    assert len(problems) == 1, lines
    return problems[0]


# --- Fluoroscope physics outside what the law or the hardware allows -------------------------------

FLUORO = "fluoroscopes/generic-ii-carm.yaml"


@pytest.mark.parametrize("old, new, anchor, expected", [
    # 21 CFR 1020.32(d)(1): 88 mGy/min in normal mode.
    ("{continuous: 8.0,", "{continuous: 1e12,", "{continuous: 1e12,", "88 mGy/min"),
    # ABC may drive the tube up to the image chain's dose-rate limit: a limit of 100 > 88.
    ("  dose_rate_limit_mgy_per_min: 88", "  dose_rate_limit_mgy_per_min: 100", "  dose_rate_limit_mgy_per_min:",
     "100 mGy/min exceeds the federal limit of 88"),
    ("  alarm_period_s: 300", "  alarm_period_s: 1e-9", "alarm_period_s", "greater than or equal to 10"),
    ("  alarm_period_s: 300", "  alarm_period_s: 600", "alarm_period_s", "less than or equal to 300"),
    ("  alarm_period_s: 300", "  alarm_period_s: .nan", "alarm_period_s", "finite number"),
    ("  level: 3.0", "  level: .inf", "  level:", "finite number"),
    ("  fx: 4444.444", "  fx: 1e-9", "  fx:", "focal length"),
    ("{k1: 2.5,", "{k1: 1e9,", "distortion:", "within 30%"),
    ("  cx: 511.5", "  cx: 1e6", "  cx:", "outside the detector"),
    ("  source_to_isocentre_mm: 620", "  source_to_isocentre_mm: 999", "source_to_isocentre_mm",
     "at least 100 mm less"),
    ("    - [1.0, 0.0, 0.0, 150.0]", "    - [1.0, 0.0, 0.0, 1e12]", "T_xray_from_webcam", "from the focal spot"),
])
def test_absurd_fluoroscope_is_refused_with_its_bound(configs, capsys, old, new, anchor, expected):
    path = configs / FLUORO
    edit(path, old, new)
    problem = one_problem(refused(["validate", str(path)], capsys))
    assert problem.startswith(f"{path}:{line_of(path, anchor)}: ")
    assert expected in problem


def test_far_sid_with_sod_one_mm_short_is_refused(configs, capsys):
    path = configs / FLUORO
    edit(path, "  source_to_image_mm: 1000", "  source_to_image_mm: 3000")
    edit(path, "  source_to_isocentre_mm: 620", "  source_to_isocentre_mm: 2999")
    edit(path, "  fx: 4444.444\n  fy: 4444.444", "  fx: 13333.3\n  fy: 13333.3")
    problems = [l for l in refused(["validate", str(path)], capsys) if "source_to_isocentre_mm" in l]
    assert len(problems) == 1 and "the patient lies between isocentre and detector" in problems[0]


def test_high_level_control_allows_176_and_no_more(configs, capsys):
    path = configs / FLUORO
    edit(path, "  enabled: true", "  enabled: false")
    edit(path, "    - name: continuous\n", "    - name: continuous\n      high_level_control: true\n")
    edit(path, "{continuous: 8.0,", "{continuous: 170.0,")
    assert main(["validate", str(path)]) == 0, capsys.readouterr().err
    edit(path, "{continuous: 170.0,", "{continuous: 180.0,")
    assert "176 mGy/min with high-level control" in one_problem(refused(["validate", str(path)], capsys))
    # Without the control the same mode is held to the normal limit.
    edit(path, "      high_level_control: true\n", "")
    assert "88 mGy/min in normal mode" in one_problem(refused(["validate", str(path)], capsys))


@pytest.mark.parametrize("old, new, expected", [
    ("[900.0, 0.0, 639.5]", "[1e9, 0.0, 639.5]", "no webcam's"),
    ("[0.0, 900.0, 359.5]", "[0.0, 900.0, 1e7]", "outside the 1280x720 image"),
    ("dist: [0.0,", "dist: [1e6,", "a webcam lens stays within"),
])
def test_absurd_webcam_is_refused(configs, capsys, old, new, expected):
    path = configs / "webcams/generic-720p.yaml"
    edit(path, old, new)
    assert expected in one_problem(refused(["validate", str(path)], capsys))


def test_wrong_kind_of_profile_is_one_line(configs, capsys, tmp_path):
    lines = refused(["render", "--volume", str(tmp_path / "none.nii"), "--fluoroscope", str(configs / FLUORO),
                     "--pose", str(configs / FLUORO), "--quantity", "display", "--output", str(tmp_path / "x.png")],
                    capsys)
    assert lines == [f"{configs / FLUORO}:1: is a fluoroscope profile, not a pose for `fluorosim render`; "
                     "check which file the command or profile names here"]


def test_a_file_of_no_kind_is_one_line_but_typos_keep_a_line_each(configs, capsys, tmp_path):
    junk = tmp_path / "pose.yaml"
    junk.write_text("a: 1\nb: 2\nc: 3\n")
    lines = refused(["render", "--volume", str(tmp_path / "none.nii"), "--fluoroscope", str(configs / FLUORO),
                     "--pose", str(junk), "--quantity", "display", "--output", str(tmp_path / "x.png")], capsys)
    assert len(lines) == 1 and "none of its keys (a, b, c)" in lines[0]
    # A fluoroscope with three typos is still a fluoroscope: each typo is named at its line.
    path = configs / FLUORO
    for old, new in (("  kvp: 75", "  kvpp: 75"), ("  ma: 2.0", "  mA: 2.0"), ("  rows: 1024", "  row: 1024")):
        edit(path, old, new)
    lines = [l for l in refused(["render", "--volume", str(tmp_path / "none.nii"), "--fluoroscope", str(path),
                                 "--pose", str(junk), "--quantity", "display", "--output", str(tmp_path / "x.png")],
                                capsys)]
    assert sum("unknown key" in l for l in lines) == 3 and all(l.startswith(f"{path}:") for l in lines)


# --- Keypad scripts -------------------------------------------------------------------------------

SCRIPT_CASES = [
    ('{"t": NaN, "hold": "pedal", "for_s": 3}', "NaN is not a number"),
    ('{"t": 1, "hold": "pedal", "for_s": Infinity}', "Infinity is not a number"),
    ('{"t": 1, "hold": "pedal", "for_s": NaN}', "NaN is not a number"),
    ('{"t": 1e12, "tap": "KEY_KP2"}', "between 0 and 86400 s"),
    ('{"t": 1, "hold": "pedal", "for_s": 1e999}', "between 0 and 86400 s"),   # json reads 1e999 as inf
    ('{"t": 1, "tap": "KEY_KP99"}', "'KEY_KP99' is no key of the keymap"),
    ('{"t": 1, "tap": "zoom_9"}', "'zoom_9' is no key of the keymap"),
]


@pytest.mark.parametrize("line, expected", SCRIPT_CASES)
def test_bad_script_line_is_refused_at_validate(configs, capsys, line, expected):
    script = configs / "scripts/demo-session.jsonl"
    with script.open("a") as f:
        f.write(line + "\n")
    n = len(script.read_text().splitlines())
    appliance = configs / "appliance-demo.yaml"
    problem = one_problem(refused(["validate", str(appliance)], capsys))
    assert problem.startswith(f"{appliance}:{line_of(appliance, 'script:')}: devices.keypad.script: {script}:{n}: ")
    assert expected in problem


@pytest.mark.parametrize("data, expected", [
    (bytes(range(256)) * 4, "is a binary file"),
    ('{"t": 1, "tap": "zoom_2"}\n'.encode("utf-16"), "is a binary file"),
    (b'{"t": 1, "tap": "caf\xe9"}\n', "is not UTF-8 text"),
])
def test_binary_script_is_one_line(tmp_path, data, expected):
    path = tmp_path / "script.jsonl"
    path.write_bytes(data)
    with pytest.raises(ScriptProblem) as e:
        ScriptedInput(path)
    assert expected in str(e.value) and "\n" not in str(e.value)


def test_demo_with_a_nan_script_refuses_quickly(configs):
    """The hang the issue reports: the demo ran 'for nan s' with the pedal held. Now it never starts."""
    (configs / "scripts/demo-session.jsonl").write_text('{"t": 2, "hold": "pedal", "for_s": NaN}\n')
    start = time.monotonic()
    result = subprocess.run([sys.executable, "-m", "appliance", "demo", "--config", str(configs / "appliance-demo.yaml")],
                            capture_output=True, text=True, timeout=60, cwd=REPO)
    assert result.returncode == 2, result.stderr
    assert time.monotonic() - start < 30
    assert "Traceback" not in result.stderr
    assert [l for l in result.stderr.splitlines() if "NaN is not a number" in l]
    assert not (configs.parent / "var/demo/ledger.sqlite").exists()


# --- Trajectories ---------------------------------------------------------------------------------

@pytest.mark.parametrize("line, expected", [
    ('{"t": 0, "position_mm": [0, 0, 550], "roll_deg": Infinity}', "Infinity is not a number"),
    ('{"t": NaN, "position_mm": [0, 0, 550]}', "NaN is not a number"),
    ('{"t": 1e12, "position_mm": [0, 0, 550]}', "'t' must be a number from"),
    ('{"t": 0, "position_mm": [0, 0, 1e999]}', "within 5000 mm of the webcam"),
    ('{"t": 0, "position_mm": [0, 0, 550], "yaw_deg": 1e300}', "'yaw_deg' must be a number from -360 to 360"),
])
def test_bad_trajectory_is_refused(configs, capsys, line, expected):
    path = configs / "trajectories/vcug-demo.jsonl"       # the demo profile's path
    path.write_text(line + "\n")
    with pytest.raises(FluorosimError, match=expected):
        load_trajectory(path)
    problem = one_problem(refused(["validate", str(configs / "appliance-demo.yaml")], capsys))
    assert "devices.camera.trajectory" in problem and expected.split("'")[0] in problem


# --- Dates given to the logs commands -------------------------------------------------------------

@pytest.fixture
def ledger(tmp_path):
    from appliance.console.state import ConsoleEvent
    from appliance.records.ledger import Ledger

    path = tmp_path / "ledger.sqlite"
    with Ledger(path) as led:
        led.start_session("trainee", "case", "fluoro", t_wall=1_700_000_000.0, t_monotonic=0.0)
        led.record([ConsoleEvent(1.0, "fluoro_on"),
                    ConsoleEvent(6.0, "fluoro_off", {}, 5.0, 0.5, 0.05, 5.0, 0.5, 0.05)])
        led.end_session(t_wall=1_700_000_010.0)
    return path


def digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.mark.parametrize("option, value", [("--since", "0001-01-01"), ("--until", "9999-12-31"),
                                           ("--since", "10000-01-01"), ("--until", "1969-06-01")])
@pytest.mark.parametrize("command", ["list", "export"])
def test_dates_out_of_range_are_one_line(ledger, tmp_path, capsys, command, option, value):
    before = digest(ledger)
    argv = ["logs", command, "--ledger", str(ledger), option, value]
    if command == "export":
        argv += ["--format", "csv", "--out", str(tmp_path / "out")]
    lines = refused(argv, capsys)
    assert len(lines) == 1 and value in lines[0] and ("1970" in lines[0] or "not a date" in lines[0])
    assert digest(ledger) == before
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("argv, names", [
    (["render", "--size", "0"], "--size"),
    (["render", "--volume", "ct.nii", "--fluoroscope", "f.yaml", "--pose", "p.yaml",
      "--quantity", "display", "--output", "o.png", "--zoom", "7"], "--zoom"),
    (["render"], "--volume"),
    (["logs", "list", "--frobnicate"], "--frobnicate"),
    (["frobnicate"], "frobnicate"),
])
def test_argument_mistakes_are_one_line(argv, names, capsys):
    """argparse's own refusals (a bad option value, a missing or unknown option) are one line
    naming the option and where the usage is, exit 2, as every other refusal is."""
    with pytest.raises(SystemExit) as exit_:
        main(argv)
    err = capsys.readouterr().err
    lines = [l for l in err.splitlines() if l.strip()]
    assert exit_.value.code == 2
    assert len(lines) == 1, err
    assert names in lines[0] and "--help" in lines[0] and "usage:" not in lines[0]


# --- Volumes that are not whole CTs in HU ---------------------------------------------------------

def ct_like(shape=(12, 14, 16), seed=0) -> np.ndarray:
    """Air around a water cylinder with a bone rod: a CT in HU."""
    z, y, x = np.indices(shape)
    r = np.hypot(y - shape[1] / 2, x - shape[2] / 2)
    hu = np.where(r < shape[1] / 3, 0.0, -1000.0) + np.random.default_rng(seed).normal(0, 10, shape)
    hu[r < 2] = 1000.0
    return hu


def write(path: Path, arr: np.ndarray, spacing=(0.8, 0.8, 2.0)) -> Path:
    image = sitk.GetImageFromArray(arr)
    image.SetSpacing(spacing)
    sitk.WriteImage(image, str(path))
    return path


def truncated(path: Path) -> Path:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    return path


def nan_voxel(arr):
    out = arr.astype(np.float32)
    out[3, 4, 5] = np.nan
    return out


VOLUME_CASES = {
    "truncated-nii-gz": (lambda p: truncated(write(p / "v.nii.gz", ct_like().astype(np.int16))), "truncated"),
    "truncated-nii": (lambda p: truncated(write(p / "v.nii", ct_like().astype(np.int16))), "is truncated: it holds"),
    "nan-nii": (lambda p: write(p / "v.nii.gz", nan_voxel(ct_like())), "1 of 2688 voxels are NaN"),
    "nan-mha": (lambda p: write(p / "v.mha", nan_voxel(ct_like())), "1 of 2688 voxels are NaN"),
    "label-map": (lambda p: write(p / "v.nii.gz", (ct_like() > -500).astype(np.uint8) + (ct_like() > 500)),
                  "label map or mask"),
    "offset-2048": (lambda p: write(p / "v.nii.gz", (ct_like() + 2048).astype(np.int16)), "rescale intercept"),
    "spacing-70mm": (lambda p: write(p / "v.nii.gz", ct_like().astype(np.int16), (0.8, 0.8, 70.0)), "no CT's"),
    "spacing-0.0007mm": (lambda p: write(p / "v.nii.gz", ct_like().astype(np.int16), (0.0007, 0.8, 2.0)), "no CT's"),
}


@pytest.mark.parametrize("name", VOLUME_CASES)
def test_volume_that_is_no_ct_is_refused(tmp_path, capsys, name):
    from appliance.patient.volume_io import load_volume

    make, expected = VOLUME_CASES[name]
    path = make(tmp_path)
    with pytest.raises(FluorosimError, match=expected) as e:
        load_volume(path)
    assert str(e.value).startswith(f"{path}: ") and "\n" not in str(e.value)


@pytest.mark.parametrize("name", ["truncated-nii-gz", "truncated-nii", "nan-nii", "spacing-70mm", "label-map",
                                  "offset-2048"])
def test_validate_opens_the_cases_volumes(configs, capsys, name):
    make, expected = VOLUME_CASES[name]
    volume = make(configs / "cases")
    case = configs / "cases/own.yaml"
    case.write_text(f"title: own CT\nphases:\n  - volume: {volume.name}\n    time_s: 0\n")
    problem = one_problem(refused(["validate", str(case)], capsys))
    assert problem.startswith(f"{case}:3: phases[0].volume: ") and expected in problem


def test_validate_refuses_a_dicom_series_with_a_gap(configs, capsys):
    from test_volume_io import write_series

    hu = ct_like((6, 8, 8)).astype(np.int16)
    write_series(configs / "cases/series", hu, positions=[0.0, 2.5, 5.0, 10.0, 12.5, 15.0])
    case = configs / "cases/own.yaml"
    case.write_text("title: own CT\nphases:\n  - volume: series\n    time_s: 0\n")
    assert "about 1 missing slice(s)" in one_problem(refused(["validate", str(case)], capsys))


@pytest.mark.parametrize("spacing, arr, expected", [
    ((0.05, 0.05, 0.05), ct_like(), "unusual for a CT"),
    ((0.8, 0.8, 2.0), np.clip(ct_like(), -200, 3000), "has no air"),
])
def test_unusual_volume_is_loaded_with_one_warning(tmp_path, caplog, spacing, arr, expected):
    from appliance.patient.volume_io import load_volume

    path = write(tmp_path / "v.nii.gz", arr.astype(np.int16), spacing)
    with caplog.at_level(logging.WARNING):
        volume = load_volume(path)
    assert volume.hu.shape == arr.shape
    assert [r.getMessage() for r in caplog.records if expected in r.getMessage()]


# --- The log file on a full disk ------------------------------------------------------------------

def test_logging_starts_and_runs_on_a_full_disk(tmp_path, capsys):
    """/dev/full answers every write with ENOSPC, as a full disk does."""
    from appliance.daemon.logqueue import start_logging

    if not Path("/dev/full").exists():
        pytest.skip("/dev/full does not exist on this machine")
    logs_dir = tmp_path / "logs"
    logs_dir.mkdir()
    (logs_dir / "fluorosim.log").symlink_to("/dev/full")
    logs = start_logging(logs_dir, stream=sys.stderr)
    try:
        assert logs.problem is not None and "No space left on device" in logs.problem
        logging.getLogger("test").warning("exposure goes on")
    finally:
        logs.stop()
    err = capsys.readouterr().err
    assert "exposure goes on" in err and "Traceback" not in err


def test_log_records_the_disk_refuses_are_counted_not_printed(tmp_path, capsys):
    from appliance.daemon.logqueue import start_logging

    logs = start_logging(tmp_path / "logs", stream=sys.stderr)
    file_handler = logs.targets[-1]
    try:
        file_handler.stream.close()
        file_handler.stream = open("/dev/full", "a")     # the disk fills while running
        for n in range(5):
            logging.getLogger("test").warning("record %d", n)
    finally:
        logs.stop()
    assert logs.failed_writes >= 5
    err = capsys.readouterr().err
    assert "record 4" in err and "Logging error" not in err and "Traceback" not in err


# --- Fuzzing the readers: any text gives one line or a valid result, never a traceback ------------

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

FUZZ = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
json_values = st.recursive(st.none() | st.booleans() | st.floats() | st.integers() | st.text(max_size=8),
                           lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner,
                                                                                       max_size=4), max_leaves=8)
script_keys = st.sampled_from(["t", "key", "tap", "hold", "for_s", "tap_s", "pressed"])


@FUZZ
@given(st.lists(st.dictionaries(script_keys, json_values, max_size=4), max_size=4))
def test_fuzz_script_lines(tmp_path, lines):
    path = tmp_path / "fuzz.jsonl"
    path.write_text("\n".join(json.dumps(line) for line in lines))
    try:
        events = ScriptedInput(path).poll(float("inf"))
    except ScriptProblem as e:
        assert "\n" not in str(e)
        return
    assert all(np.isfinite(ev.t) and 0 <= ev.t <= 2 * 86_400 for ev in events)


traj_keys = st.sampled_from(["t", "position_mm", "roll_deg", "tilt_deg", "yaw_deg", "T_webcam_from_phantom"])


@FUZZ
@given(st.lists(st.dictionaries(traj_keys, json_values | st.lists(st.floats(), min_size=3, max_size=3),
                                max_size=5), min_size=1, max_size=3))
def test_fuzz_trajectory_lines(tmp_path, lines):
    path = tmp_path / "fuzz.jsonl"
    path.write_text("\n".join(json.dumps(line) for line in lines))
    try:
        trajectory = load_trajectory(path)
    except FluorosimError as e:
        assert "\n" not in str(e)
        return
    assert np.all(np.isfinite(trajectory(0.5)))


yaml_scalars = st.one_of(st.floats(), st.integers(), st.booleans(), st.none(), st.text(max_size=6),
                         st.sampled_from([".nan", ".inf", "-.inf", "1e999", "0x10", "~", "[", "{a: 1"]))
FLUORO_FIELDS = ["  fx: 4444.444", "  cx: 511.5", "  alarm_period_s: 300", "  source_to_image_mm: 1000",
                 "  max_factor: 4.0", "  columns: 1024", "  level: 3.0", "  pixel_pitch_mm: 0.225"]


@FUZZ
@given(st.sampled_from(FLUORO_FIELDS), yaml_scalars)
def test_fuzz_fluoroscope_values(tmp_path, field, value):
    from appliance.config import FluoroscopeProfile, ProfileProblems, load_profile

    text = (CONFIGS / FLUORO).read_text()
    key = field.split(":")[0]
    path = tmp_path / "fluoroscopes" / "f.yaml"
    path.parent.mkdir(exist_ok=True)
    path.write_text(text.replace(field, f"{key}: {value}", 1))
    try:
        profile = load_profile(path, FluoroscopeProfile)
    except ProfileProblems as e:
        assert e.problems and all("\n" not in str(p) and str(p).startswith(str(path)) for p in e.problems)
        return
    # Accepted: then every number is finite and within the federal dose-rate limit.
    rates = [r for z in profile.zoom_levels for r in z.air_kerma_rate_mgy_per_min.values()]
    # (the exposure control drives the tube to max_factor x a rate, but never past the chain's limit)
    assert min(max(rates) * profile.abc.max_factor, profile.image.dose_rate_limit_mgy_per_min) <= 88
    assert max(rates) <= 88
    assert 10 <= profile.dose.alarm_period_s <= 300
    assert np.isfinite([profile.intrinsics.fx, profile.intrinsics.cx, profile.display.level]).all()


def test_nifti_stored_unsigned_with_its_intercept_is_a_ct(tmp_path):
    """A scanner's unsigned voxels with scl_inter = -1024 in the header are HU once rescaled:
    accepted at validate (which reads the header's rescale itself) and at load."""
    import gzip
    import struct

    from appliance.patient.volume_checks import check_header
    from appliance.patient.volume_io import load_volume

    hu = np.clip(ct_like(), -1024, 3000).astype(np.int16)     # what an unsigned store with -1024 can hold
    path = write(tmp_path / "v.nii", hu)
    data = bytearray(path.read_bytes())
    offset = int(struct.unpack("<f", data[108:112])[0])
    data[70:72] = struct.pack("<h", 512)                      # datatype: uint16
    data[112:120] = struct.pack("<ff", 1.0, -1024.0)          # scl_slope, scl_inter
    data[offset:] = (hu.astype(np.int32) + 1024).astype("<u2").tobytes()
    gz = tmp_path / "unsigned.nii.gz"
    gz.write_bytes(gzip.compress(bytes(data)))
    assert check_header(gz) == ([], [])
    assert int(load_volume(gz).hu.min()) == int(hu.min())
    # Without the intercept the same bytes are no CT, and validate says why.
    data[112:120] = struct.pack("<ff", 1.0, 0.0)
    gz.write_bytes(gzip.compress(bytes(data)))
    assert "rescale intercept" in check_header(gz)[0][0]
