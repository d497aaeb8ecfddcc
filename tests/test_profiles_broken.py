"""Broken profiles: each gives exit 2 and one line naming the file, the line and the field.

The expected line is found in the broken file's own text (where a person would look),
independently of the loader under test.
"""

import re
import shutil
import subprocess
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pytest

from appliance.cli import main

REPO = Path(__file__).resolve().parents[1]
CONFIGS = REPO / "configs"

FLUORO = "fluoroscopes/generic-ii-carm.yaml"
CASE = "cases/child-torso-vcug.yaml"
PHANTOM = "phantoms/box-v1.yaml"
KEYMAP = "keymaps/usb-numeric-keypad.yaml"
WEBCAM = "webcams/generic-720p.yaml"
APPLIANCE = "appliance.yaml"


def replace(old: str, new: str) -> Callable[[str], str]:
    def edit(text: str) -> str:
        assert old in text, f"test setup: {old!r} not in the shipped profile"
        return text.replace(old, new, 1)
    return edit


def raw(data: bytes) -> Callable[[str], bytes]:
    return lambda _text: data


@dataclass
class Broken:
    name: str
    file: str                       # profile (relative to configs/) that is broken
    edit: Callable[[str], str | bytes]
    anchor: str | None              # text on the line the error must point at (None: line 1 or none)
    field: str                      # what the message must name
    validate: str | None = None     # file to validate, when the error is found through a reference

    def line(self, text: str) -> int | None:
        if self.anchor is None:
            return None
        hits = [i + 1 for i, l in enumerate(text.splitlines()) if self.anchor in l]
        assert hits, f"test setup: anchor {self.anchor!r} not found"
        return hits[0]


CASES = [
    Broken("yaml-syntax", FLUORO, replace("  columns: 1024", "  columns: [1024"), "rows: 1024", "YAML syntax error"),
    Broken("empty-file", FLUORO, raw(b""), None, "is empty"),
    Broken("only-comments", KEYMAP, raw(b"# nothing here\n\n# at all\n"), None, "is empty"),
    Broken("binary-garbage", PHANTOM, raw(bytes(range(256)) * 40), None, "binary"),
    Broken("five-megabytes", CASE, raw(b"# padding\n" * 500_000), None, "MB"),
    Broken("not-utf8", WEBCAM, raw("name: Caméra\n".encode("latin-1")), None, "UTF-8"),
    Broken("top-level-list", KEYMAP, raw(b"- KEY_F1: fluoro\n"), None, "mapping"),
    Broken("wrong-type", FLUORO, replace("pixel_pitch_mm: 0.225", "pixel_pitch_mm: small"), "pixel_pitch_mm: small", "detector.pixel_pitch_mm"),
    Broken("missing-key", FLUORO, replace("  rows: 1024\n", ""), "detector:", "detector.rows"),
    Broken("unknown-key", FLUORO, replace("  kvp: 75", "  kvp: 75\n  kvpp: 80"), "kvpp: 80", "tube.kvpp"),
    Broken("negative-pitch", FLUORO, replace("pixel_pitch_mm: 0.225", "pixel_pitch_mm: -0.225"), "pixel_pitch_mm: -0.225", "detector.pixel_pitch_mm"),
    Broken("zero-fov", FLUORO, replace("fov_mm: 130", "fov_mm: 0"), "fov_mm: 0", "zoom_levels[2].fov_mm"),
    Broken("zoom-out-of-order", FLUORO, replace("fov_mm: 130", "fov_mm: 200"), "fov_mm: 200", "zoom_levels[2].fov_mm"),
    Broken("three-zoom-levels", FLUORO, replace("  - fov_mm: 100\n    air_kerma_rate_mgy_per_min: {continuous: 42.3, pulsed-15: 21.2, pulsed-7.5: 10.6}\n", ""),
           "zoom_levels:", "zoom_levels"),
    Broken("rate-for-unknown-mode", FLUORO, replace("{continuous: 14.6, pulsed-15: 7.3, pulsed-7.5: 3.7}", "{continuous: 14.6, pulsed-15: 7.3}"),
           "{continuous: 14.6, pulsed-15: 7.3}", "zoom_levels[1].air_kerma_rate_mgy_per_min"),
    Broken("isocentre-beyond-detector", FLUORO, replace("source_to_isocentre_mm: 620", "source_to_isocentre_mm: 1200"),
           "source_to_isocentre_mm: 1200", "geometry.source_to_isocentre_mm"),
    Broken("falling-kv-curve", FLUORO, replace("    - {kvp: 90, ma: 3.0}", "    - {kvp: 70, ma: 3.0}"), "{kvp: 70, ma: 3.0}", "abc.curve[2]"),
    Broken("bad-detector-kind", FLUORO, replace("kind: image_intensifier", "kind: ccd"), "kind: ccd", "detector.kind"),
    Broken("non-rigid-scale", FLUORO, replace("    - [0.0, -1.0, 0.0, 0.0]", "    - [0.0, -1.2, 0.0, 0.0]"), "T_xray_from_webcam:", "webcam.T_xray_from_webcam"),
    Broken("mirror-transform", CASE, replace("  - [0, 0, 1, 0]", "  - [0, 0, -1, 0]"), "T_phantom_from_ct:", "T_phantom_from_ct"),
    Broken("transform-3x4", CASE, replace("  - [0, 0, 0, 1]\nmaterials", "materials"), "T_phantom_from_ct:", "T_phantom_from_ct"),
    Broken("duplicate-marker-id", PHANTOM, replace("  - id: 7    # side +y", "  - id: 6    # stuck on twice"), "stuck on twice", "markers[7].id"),
    Broken("root-marker-missing", PHANTOM, replace("root_marker_id: 0", "root_marker_id: 42"), "root_marker_id: 42", "root_marker_id"),
    Broken("marker-not-in-dictionary", PHANTOM, replace("  - id: 13 ", "  - id: 77 "), "  - id: 77 ", "markers[13].id"),
    Broken("unknown-dictionary", PHANTOM, replace("DICT_4X4_50", "DICT_9X9_50"), "DICT_9X9_50", "aruco_dictionary"),
    Broken("unknown-action", KEYMAP, replace("KEY_KP5: mode_next", "KEY_KP5: self_destruct"), "KEY_KP5: self_destruct", "keys.KEY_KP5"),
    Broken("bad-key-name", KEYMAP, replace("KEY_KP5: mode_next", "kp5: mode_next"), "kp5: mode_next", "keys.kp5"),
    Broken("duplicate-yaml-key", KEYMAP, replace("  KEY_KP2: zoom_2", "  KEY_KP1: zoom_2"), "KEY_KP1: zoom_2", "duplicate key"),
    Broken("phase-times-not-increasing", CASE,
           replace("builtin: child-torso", "phases:\n  - {volume: a.nii.gz, time_s: 1.0}\n  - {volume: a.nii.gz, time_s: 0.5}"),
           "time_s: 0.5", "phases[1].time_s"),
    Broken("dangling-volume", CASE, replace("builtin: child-torso", "phases:\n  - {volume: ../volumes/missing.nii.gz, time_s: 0}"),
           "missing.nii.gz", "phases[0].volume"),
    Broken("builtin-and-phases", CASE, replace("builtin: child-torso", "builtin: child-torso\nphases:\n  - {volume: case.yaml, time_s: 0}"),
           "phases:", "phases"),
    Broken("moving-matrix-ladder-upside-down", "appliance-demo.yaml",
           replace("moving_matrix_min_px: 128", "moving_matrix_min_px: 384"), "rendering:", "moving_matrix_min_px (384)"),
    Broken("rest-hold-inside-the-cache-tolerance", "appliance-demo.yaml",
           replace("rest_hold_px: 1.0 ", "rest_hold_px: 0.1 "), "rendering:", "rest_hold_px (0.1)"),
    Broken("webcam-K-not-3x3", WEBCAM, replace("  - [0.0, 0.0, 1.0]\n", ""), "K:", "K"),
    Broken("camera-nice-out-of-range", APPLIANCE, replace("    synthetic_nice: 10", "    synthetic_nice: 25"),
           "synthetic_nice", "devices.camera.synthetic_nice"),
    Broken("dangling-profile", APPLIANCE, replace("fluoroscopes/generic-ii-carm.yaml", "fluoroscopes/nope.yaml"), "fluoroscopes/nope.yaml", "fluoroscope"),
    Broken("scripted-keypad-without-script", APPLIANCE, replace("    source: none\n  pedal", "    source: scripted\n  pedal"),
           "source: scripted", "devices.keypad.script"),
    Broken("broken-through-reference", FLUORO, replace("  ma: 2.0", "  ma: -2.0"), "ma: -2.0", "tube.ma", validate=APPLIANCE),
]


def make_broken(case: Broken, root: Path) -> tuple[Path, Path, str | bytes]:
    configs = root / "configs"
    shutil.copytree(CONFIGS, configs)
    target = configs / case.file
    content = case.edit(target.read_text())
    (target.write_bytes if isinstance(content, bytes) else target.write_text)(content)
    return target, configs / (case.validate or case.file), content


def test_there_are_at_least_25_broken_profiles():
    assert len(CASES) >= 25


@pytest.mark.parametrize("case", CASES, ids=lambda c: c.name)
def test_broken_profile_is_refused_with_file_line_and_field(case: Broken, tmp_path, capsys):
    target, validated, content = make_broken(case, tmp_path)
    assert main(["validate", str(validated)]) == 2
    out, err = capsys.readouterr()
    lines = [l for l in err.splitlines() if not re.fullmatch(r"\d+ problem\(s\) found", l)]
    assert lines, "no problem reported"
    assert "Traceback" not in err
    mine = [l for l in lines if l.startswith(f"{target}:") or l.startswith(f"{target}: ")]
    assert mine, f"no line names {target.name}: {lines}"
    text = content.decode("latin-1") if isinstance(content, bytes) else content
    expected_line = case.line(text)
    if expected_line is not None:
        assert any(l.startswith(f"{target}:{expected_line}: ") for l in mine), f"expected line {expected_line}: {mine}"
    assert any(case.field in l for l in mine), f"expected {case.field!r} in {mine}"


def test_broken_profiles_give_no_traceback_from_the_real_command(tmp_path):
    paths = []
    for i, case in enumerate(CASES):
        _, validated, _ = make_broken(case, tmp_path / str(i))
        paths.append(str(validated))
    result = subprocess.run([sys.executable, "-m", "appliance", "validate", *paths], cwd=REPO,
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 2
    assert "Traceback" not in result.stderr
    for p in paths:
        assert p in result.stderr or any(f"/{i}/configs/" in l for l in result.stderr.splitlines()), p


def test_missing_path_is_one_line(capsys):
    assert main(["validate", "no/such/profile.yaml"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no/such/profile.yaml" in err[0]
