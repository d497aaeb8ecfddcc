"""The daemon's building blocks: LatestValue hand-off, health checks, the log queue, profile reload."""

from __future__ import annotations

import logging
import os
import shutil
import threading
import time
from pathlib import Path

import pytest

from appliance import __version__
from appliance.config import ProfileProblems
from appliance.daemon.handoff import LatestValue
from appliance.daemon.health import (
    CameraState,
    DiskSpace,
    InputDeviceState,
    Level,
    profile_reload_check,
    records_check,
    renderer_fault_check,
)
from appliance.daemon.logqueue import start_logging
from appliance.daemon.reload import ProfileKeeper
from appliance.daemon.worker import Worker

CONFIGS = Path(__file__).resolve().parents[1] / "configs"


# --- LatestValue ---------------------------------------------------------------------------

def test_latest_value_gives_the_newest_and_counts_what_was_skipped():
    slot: LatestValue[int] = LatestValue()
    assert slot.get() == (None, 0)
    assert slot.newer(0) is None
    for i in range(1, 6):
        slot.put(i * 10)
    assert slot.get() == (50, 5)
    assert slot.dropped == 4  # 10..40 were overwritten unread
    assert slot.newer(5) is None
    slot.put(60)
    assert slot.newer(5) == (60, 6)
    assert slot.dropped == 4


def test_a_slow_reader_skips_stale_values_instead_of_falling_behind():
    slot: LatestValue[tuple[int, float]] = LatestValue()
    n, period = 200, 0.002
    done = threading.Event()

    def produce():
        for i in range(1, n + 1):
            slot.put((i, time.monotonic()))
            time.sleep(period)
        done.set()

    seen, ages = [], []
    t = threading.Thread(target=produce)
    t.start()
    seq = 0
    while not (done.is_set() and slot.seq == seq):
        got = slot.wait_newer(seq, 0.5)
        if got is None:
            continue
        (i, stamped), seq = got
        seen.append(i)
        ages.append(time.monotonic() - stamped)
        time.sleep(0.02)  # ten times slower than the producer
    t.join()
    assert seen == sorted(set(seen))  # always forward, never an old value twice
    assert seen[-1] == n
    assert len(seen) < n / 3
    assert slot.dropped == n - len(seen)
    # Each value read was the newest at the time: never more than a couple of producer periods old.
    assert sorted(ages)[len(ages) // 2] < 0.01


def test_wait_newer_times_out():
    slot: LatestValue[int] = LatestValue()
    t0 = time.monotonic()
    assert slot.wait_newer(0, 0.1) is None
    assert 0.09 <= time.monotonic() - t0 < 0.5


# --- Worker heartbeat ------------------------------------------------------------------------

def test_grace_covers_a_known_long_step():
    clock = [100.0]
    w = Worker("loader", lambda w: False, clock=lambda: clock[0])
    w.beat()
    clock[0] = 103.0
    assert w.stall_s() == pytest.approx(3.0)
    with w.grace(30.0):
        clock[0] = 120.0
        assert w.stall_s() == 0.0
        clock[0] = 140.0
        assert w.stall_s() == pytest.approx(7.0)  # the grace ran out at 133
    assert w.stall_s() == 0.0  # leaving the block beats


# --- Health checks ----------------------------------------------------------------------------

def test_disk_space_against_statvfs(tmp_path):
    st = os.statvfs(tmp_path)
    free_mb = st.f_bavail * st.f_frsize / 2**20
    ok = DiskSpace(tmp_path, min_free_mb=0).check()
    assert ok.level == Level.OK
    assert ok.context["free_mb"] == pytest.approx(free_mb, abs=64)
    full = DiskSpace(tmp_path, min_free_mb=free_mb + 10_000).check()
    assert full.level == Level.WARNING and full.banner.startswith("disk nearly full")
    missing = DiskSpace(tmp_path / "gone", min_free_mb=0).check()
    assert missing.level == Level.ERROR and "data folder" in missing.banner


class _Device:
    def __init__(self, state):
        self.state = state


def test_device_states_map_to_banners():
    cam = _Device("ok")
    check = CameraState(lambda: cam)
    assert check.check().ok
    cam.state = "camera lost"
    assert check.check().banner.startswith("tracking lost")
    cam.state = "starting"
    assert check.check().level == Level.WARNING
    assert CameraState(lambda: None).check().level == Level.WARNING

    pedal = _Device("unplugged")
    assert InputDeviceState("pedal", lambda: pedal).check().banner == "pedal unplugged - plug it back in"
    pedal.problem = "/dev/fluorosim/pedal: pedal silent for more than 0.5 s; counted as released"
    assert InputDeviceState("pedal", lambda: pedal).check().banner == f"pedal: {pedal.problem}"
    pedal.state = "ok"
    assert InputDeviceState("pedal", lambda: pedal).check().ok
    assert InputDeviceState("keypad", lambda: _Device("none")).check().ok
    assert renderer_fault_check(lambda: None).check().ok
    assert "CPU" in renderer_fault_check(lambda: "clBuildProgram failed").check().banner
    assert profile_reload_check(lambda: "x.yaml:3: a: bad").check().banner.endswith("x.yaml:3: a: bad")
    records = records_check(lambda: "ledger.sqlite: disk full").check()
    assert records.level == Level.ERROR and records.banner.endswith("ledger.sqlite: disk full")


# --- Logging ----------------------------------------------------------------------------------

def test_log_file_starts_with_the_version_header_and_gets_every_thread(tmp_path):
    root = logging.getLogger()
    before = list(root.handlers), root.level
    logs = start_logging(tmp_path / "logs", stream=open(os.devnull, "w"))
    try:
        def talk(k):
            for i in range(50):
                logging.getLogger("test.worker").info("worker %d line %d", k, i)

        threads = [threading.Thread(target=talk, args=(k,)) for k in range(4)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    finally:
        logs.stop()
        root.handlers[:] = before[0]
        root.setLevel(before[1])
    text = (tmp_path / "logs" / "fluorosim.log").read_text()
    first = text.splitlines()[0]
    assert first.startswith(f"# fluorosim {__version__} | Python ")
    assert f"pid {os.getpid()}" in first
    for k in range(4):
        for i in (0, 49):
            assert f"worker {k} line {i}" in text
    assert logs.dropped == 0


# --- Profile reload ---------------------------------------------------------------------------

@pytest.fixture
def configs(tmp_path):
    shutil.copytree(CONFIGS, tmp_path / "configs")
    return tmp_path / "configs"


def test_bad_edit_keeps_the_last_good_profiles(configs):
    keeper = ProfileKeeper(configs / "appliance.yaml")
    good = keeper.current
    fl = configs / "fluoroscopes" / "generic-ii-carm.yaml"
    text = fl.read_text()
    lines = text.splitlines()
    line_no = next(i for i, l in enumerate(lines) if "source_to_image_mm:" in l) + 1
    fl.write_text(text.replace("source_to_image_mm: 1000", "source_to_image_mm: -5"))
    config, changed = keeper.reload()
    assert not changed and config is good
    assert f"generic-ii-carm.yaml:{line_no}: geometry.source_to_image_mm" in keeper.problem
    fl.write_text(text.replace("name: Generic II C-arm", "name: Renamed C-arm"))
    config, changed = keeper.reload()
    assert changed and keeper.problem is None
    assert config.fluoroscope.name == "Renamed C-arm" and keeper.generation == 2


def test_a_bad_profile_at_start_is_one_clear_error(configs):
    (configs / "appliance.yaml").write_text((configs / "appliance.yaml").read_text().replace("operator: trainee", "operater: x"))
    with pytest.raises(ProfileProblems) as e:
        ProfileKeeper(configs / "appliance.yaml")
    assert "did you mean 'operator'" in str(e.value)


# --- Clock and frame statistics -----------------------------------------------------------------

def test_sim_clock_runs_at_its_rate():
    from appliance.daemon.clock import SimClock
    wall = [50.0]
    clock = SimClock(6.0, base=lambda: wall[0])
    assert clock() == 50.0
    wall[0] = 60.0
    assert clock() == pytest.approx(50.0 + 60.0)
    assert clock.wall_s(30.0) == pytest.approx(5.0)
    with pytest.raises(ValueError):
        SimClock(0)


def test_frame_stats_against_hand_worked_numbers():
    from appliance.daemon.frame_stats import FrameStats
    stats = FrameStats(window_s=1.0)
    # 101 frames 0.1 s apart (10 fps), latency k ms for frame k (k = 0..100).
    for k in range(101):
        stats.add(100.0 + 0.1 * k, k / 1000)
    s = stats.summary()
    assert s["frames"] == 101
    assert s["fps"] == pytest.approx(10.0)
    assert s["latency_median_ms"] == pytest.approx(50.0)
    assert s["latency_p99_ms"] == pytest.approx(99.0)
    # The last second holds frames at 109.0 .. 110.0: 11 frames over a 1 s window.
    assert stats.fps(110.0) == pytest.approx(11.0)
    assert stats.fps(200.0) == 0.0


def test_case_override_replaces_only_the_case(configs):
    other = configs / "cases" / "other.yaml"
    other.write_text((configs / "cases" / "child-torso-vcug.yaml").read_text().replace(
        "title: Child torso - VCUG and breathing", "title: Another case"))
    keeper = ProfileKeeper(configs / "appliance.yaml", case=other)
    assert keeper.current.case.title == "Another case" and keeper.current.case_path == other
    assert keeper.current.fluoroscope.name == "Generic II C-arm"
    other.write_text(other.read_text().replace("period_s: 4.0", "period_s: -4.0"))
    config, changed = keeper.reload()
    assert not changed and "other.yaml" in keeper.problem and "breathing.period_s" in keeper.problem
    with pytest.raises(ProfileProblems):
        ProfileKeeper(configs / "appliance.yaml", case=configs / "cases" / "missing.yaml")


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
