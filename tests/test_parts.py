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
    # On a CPU device a profile without a matrix renders the CPU's; one that names a matrix keeps it.
    assert rendered_fluoroscope(cfg, cpu=True).detector.columns == daemon.cpu_fallback_matrix_px == 256
    assert rendered_fluoroscope(with_daemon(render_matrix_px=512), cpu=True).detector.columns == 512
    assert rendered_fluoroscope(with_daemon(cpu_fallback_matrix_px=2048), cpu=True) is cfg.fluoroscope


def test_without_a_gpu_the_real_profile_renders_the_cpu_matrix_and_says_so(caplog):
    """configs/appliance.yaml names no render_matrix_px (a GPU renders the detector's 1024): where
    the OpenCL device picked is PoCL's CPU device, the appliance renders daemon.cpu_fallback_matrix_px
    and logs one line a service technician can act on; `bench e2e` measured 1.7 frames/s and
    726 ms median latency for this profile's 1024 on two CPU cores."""
    import logging

    from appliance.config import load_appliance
    from appliance.daemon.parts import make_renderer
    from appliance.xray.device import is_cpu_device, pick_device

    if not is_cpu_device(pick_device("auto")):
        pytest.skip("this machine has a GPU: the appliance renders the detector's matrix there")
    cfg = load_appliance(CONFIGS / "appliance.yaml")
    assert cfg.appliance.daemon.render_matrix_px is None and cfg.fluoroscope.detector.columns == 1024
    with caplog.at_level(logging.WARNING, logger="appliance.daemon.parts"):
        progressive = make_renderer(cfg)
    assert progressive.full.shape == (256, 256)
    lines = [r.getMessage() for r in caplog.records if r.name == "appliance.daemon.parts"]
    assert len(lines) == 1 and "256 x 256 (daemon.cpu_fallback_matrix_px)" in lines[0]
    assert "1024 x 1024 needs a GPU" in lines[0] and "daemon.render_matrix_px" in lines[0]
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="appliance.daemon.parts"):
        assert make_renderer(cfg, "cpu").full.shape == (256, 256)     # the fall-back after a failed GPU: its own banner
    assert not [r for r in caplog.records if r.name == "appliance.daemon.parts"]


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


def test_the_live_renderer_fits_a_new_kv_on_the_side_thread_at_every_matrix(monkeypatch):
    """The daemon's renderer (and its renderers at other matrices) does not stall a frame for a kV's
    energy-node fit: at a kV fitted nowhere yet its tables sum every bin, awaiting the nodes,
    and once the side thread's fit is in, the same kV is summed at the nodes."""
    import appliance.xray.energy_nodes as energy_nodes
    from appliance.config import load_appliance
    from appliance.daemon.parts import make_renderer

    monkeypatch.setattr(energy_nodes, "_FITS", {})
    cfg = load_appliance(CONFIGS / "appliance.yaml")
    assert cfg.fluoroscope.energy_nodes.enabled
    progressive = make_renderer(cfg, "cpu")
    casters = [progressive.full.caster, progressive.full.at_matrix(64, 64).caster]
    casters += [m.caster for m in progressive._movers.values()]
    for caster in casters:
        tables = caster.tables()
        assert tables.awaiting_nodes and tables.quadrature is None
        assert tables.device_bins == len(tables.weights)
    kv = float(cfg.fluoroscope.tube.kvp)
    progressive.full.caster._fitting[kv].result(timeout=60)
    assert progressive.full.caster.tables().quadrature is not None
