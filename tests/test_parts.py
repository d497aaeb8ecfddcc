"""parts: the fluoroscope as rendered, at daemon.render_matrix_px and after a CPU fallback."""

from __future__ import annotations

from pathlib import Path

import pytest

CONFIGS = Path(__file__).resolve().parents[1] / "configs"


def test_render_matrix_and_cpu_fallback_scale_the_fluoroscope():
    import dataclasses

    from appliance.config import load_appliance
    from appliance.daemon.parts import rendered_fluoroscope

    cfg = load_appliance(CONFIGS / "appliance.yaml")
    assert rendered_fluoroscope(cfg) is cfg.fluoroscope  # 1024 x 1024 as the detector
    daemon = cfg.appliance.daemon

    def with_daemon(**kw):
        return dataclasses.replace(cfg, appliance=cfg.appliance.model_copy(update={"daemon": daemon.model_copy(update=kw)}))

    fl = rendered_fluoroscope(with_daemon(render_matrix_px=256))
    # A quarter of the matrix: four times the pixel pitch, a quarter of the focal length in pixels,
    # the same 230 mm field (256 x 0.9 mm).
    assert (fl.detector.columns, fl.detector.rows) == (256, 256)
    assert fl.detector.pixel_pitch_mm == pytest.approx(0.225 * 4)
    assert fl.intrinsics.fx == pytest.approx(4444.444 / 4)
    assert fl.intrinsics.cx == pytest.approx((511.5 + 0.5) / 4 - 0.5)
    assert rendered_fluoroscope(cfg, fallback=True).detector.columns == daemon.cpu_fallback_matrix_px
    assert rendered_fluoroscope(with_daemon(render_matrix_px=128), fallback=True).detector.columns == 128


def test_the_screen_file_is_under_the_data_dir_in_force(tmp_path):
    import os

    from appliance.daemon.reload import ProfileKeeper
    from appliance.display.target import screen_file

    profile = Path(__file__).resolve().parents[1] / "configs" / "appliance-bench.yaml"
    cfg = ProfileKeeper(profile, data_dir=tmp_path / "out").current     # as `bench e2e --out` runs it
    assert screen_file(cfg.path, cfg.appliance, cfg.data_dir) == tmp_path / "out" / "screen.raw"
    # Without an override, the profile's own data_dir (../var/bench from configs/).
    written = screen_file(cfg.path, cfg.appliance)
    assert written is not None
    assert os.path.normpath(written) == os.path.normpath(profile.parent / ".." / "var" / "bench" / "screen.raw")
