"""A saved image's native re-render beside the live view (appliance/daemon/native_save.py).

Ground truth: the pacing's waits worked by hand from the share (a band of 60 ms at share
0.5 is followed by 60 ms for the live view; at share 1, none; with no live frame coming,
none), the caller's callback asked every slice of the wait, and a dose event put in the
queue while the save is being cast written to a real SQLite ledger before the save ends,
with the run's hand-made air kerma (1.5 mGy) and the saved image's file on disk.
"""

from __future__ import annotations

import dataclasses
import queue
import time
import types
from pathlib import Path

import numpy as np
import pytest

from appliance.config import KeymapProfile
from appliance.config.case import Materials
from appliance.config.fluoroscope import FluoroscopeProfile
from appliance.config.loading import load_profile
from appliance.console.state import Console, ConsoleEvent
from appliance.daemon.handoff import LatestValue, Recorded, ShownImage
from appliance.daemon.native_save import PACE_SLICE_S, SavePacer, native_frame
from appliance.daemon.records_worker import RecordsWorker
from appliance.daemon.reload import ProfileKeeper
from appliance.records.deferred_ledger import open_ledger
from appliance.records.ledger import open_readonly
from appliance.xray import acceptance
from appliance.xray.renderer import Renderer, View, at_resolution
from appliance.xray.truth.analytic import box_volume

REPO = Path(__file__).resolve().parents[1]
II = load_profile(REPO / "configs/fluoroscopes/generic-ii-carm.yaml", FluoroscopeProfile)
BAND_S = 0.06


class Clock:
    """Simulated time: sleeping advances it, so the waits are exact."""

    def __init__(self):
        self.t = 0.0

    def __call__(self) -> float:
        return self.t

    def sleep(self, s: float) -> None:
        self.t += s


def paced(share: float, live: bool, stop_at: int = 0) -> tuple[bool, float, list[float]]:
    """What the pacer answers after a band of BAND_S, how long it held the save, and when it
    asked the callback (which says stop at its `stop_at`-th ask)."""
    clock, asked = Clock(), []

    def cancelled() -> bool:
        asked.append(clock.t)
        return len(asked) == stop_at
    pacer = SavePacer(share, cancelled, lambda: live, clock, clock.sleep)
    clock.sleep(BAND_S)                       # the band being cast
    t0 = clock.t
    answer = pacer()
    return answer, clock.t - t0, [t - t0 for t in asked]


@pytest.mark.parametrize("share, live, wait", [(0.5, True, BAND_S), (0.25, True, 3 * BAND_S),
                                               (1.0, True, 0.0), (0.25, False, 0.0)])
def test_the_save_waits_its_share_while_live_frames_come(share, live, wait):
    """After a band of 60 ms the live view gets (1 - share) / share of it: 60 ms at 0.5, 180 ms
    at 0.25, nothing at 1 or with no live frame coming; the callback is asked at once and then
    after every slice of 20 ms (3 and 9 slices)."""
    answer, held, asked = paced(share, live)
    assert answer is False
    assert held == pytest.approx(wait, abs=1e-9)
    slices = round(wait / PACE_SLICE_S)
    assert asked == pytest.approx([k * PACE_SLICE_S for k in range(slices + 1)], abs=1e-9)


def test_a_cancel_asked_during_the_wait_ends_it_at_once():
    """At share 0.1 the wait would be 540 ms; the third ask says stop, after two slices (40 ms)."""
    answer, held, asked = paced(0.1, True, stop_at=3)
    assert answer is True and held == pytest.approx(2 * PACE_SLICE_S) and len(asked) == 3


def test_the_wait_follows_the_band_it_came_after():
    """Two bands of 60 ms and 20 ms at share 0.5: waits of 60 ms and then 20 ms, each measured
    from the end of the wait before (not from the pacer's start)."""
    clock = Clock()
    pacer = SavePacer(0.5, lambda: False, lambda: True, clock, clock.sleep)
    waits = []
    for band in (0.06, 0.02):
        clock.sleep(band)
        t0 = clock.t
        pacer()
        waits.append(clock.t - t0)
    assert waits == pytest.approx([0.06, 0.02], abs=1e-9)


def test_dose_events_reach_the_ledger_while_an_image_is_saved(tmp_path):
    """The save press, then a run's end arriving while its image is re-rendered (in 6 paced
    bands on the CPU device): the run is in the ledger before the save is done."""
    keeper = ProfileKeeper(REPO / "configs/appliance-demo.yaml", data_dir=tmp_path)
    daemon = keeper.current.appliance.daemon.model_copy(update={"save_bands": 6, "save_device_share": 0.5})
    fixed = II.model_copy(update={"abc": II.abc.model_copy(update={"enabled": False})})   # one spectrum's tables
    live = Renderer(at_resolution(fixed, 24, 24), Materials(), device="cpu")
    native_fl = at_resolution(fixed, 48, 48)
    volume = box_volume((40, 40, 40), (2.0, 2.0, 2.0), (5, 5, 5), (34, 34, 34))[0]
    prepared = live.prepare(volume)
    T = acceptance.ap_pose(II.geometry.source_to_isocentre_mm)
    request = (prepared, T, View(noise=False, temporal="live"), None)
    events: queue.Queue = queue.Queue()
    seen: list[float | None] = []

    def native(cancelled):
        def between() -> bool:
            if len(seen) == 1:                # during the save: the run ends, 12 s and 1.5 mGy
                events.put(Recorded(ConsoleEvent(113.0, "fluoro_off", {}, 12.0, 1.5, 0.15, 12.0, 1.5, 0.15)))
            stop = cancelled()
            conn = open_readonly(tmp_path / "ledger.sqlite")
            seen.append(conn.execute("SELECT sum(d_air_kerma_mgy) FROM events").fetchone()[0])
            conn.close()
            return stop
        got, pacer = native_frame(live, request, native_fl, daemon, True, between, lambda: True)
        assert pacer is not None and got[0].shape == (48, 48)
        return got

    ledger = open_ledger(tmp_path / "ledger.sqlite")
    shown: LatestValue[ShownImage] = LatestValue()
    shown.put(ShownImage(np.full((24, 24), 0.5, np.float32), T))
    worker = RecordsWorker(ledger, keeper, types.SimpleNamespace(renderer=live), lambda: 100.0, events=events,
                           shown=shown, saves=LatestValue(), native=native)
    worker.setup()
    console = Console(II, load_profile(REPO / "configs/keymaps/usb-numeric-keypad.yaml", KeymapProfile), t0=100.0)
    events.put(Recorded(ConsoleEvent(101.0, "fluoro_on")))
    events.put(Recorded(ConsoleEvent(102.0, "save"), console.snapshot()))
    assert worker.step()
    assert len(seen) >= 6
    # Not in the ledger before it was put in the queue; in it from the next ask on, the save still running.
    assert seen[0] in (None, 0.0) and seen[1] == pytest.approx(1.5) and seen[-1] == pytest.approx(1.5)
    (png, dicom), = worker.saved
    assert png.exists() and dicom.exists()
    worker.stop()
    worker.teardown()
    ledger.close()


def test_bench_save_measures_the_three_conditions(capsys):
    """`fluorosim bench save` end to end on a small detector (96 px native, 32 px live): each
    condition's row with a live rate, and a save duration for the two saves."""
    from appliance.cli import build_parser
    from appliance.config.loading import load_appliance
    from appliance.daemon.save_bench import run_save_bench

    args = build_parser().parse_args(["bench", "save", "--matrix", "64", "--repeats", "2"])
    assert (args.matrix, args.repeats, args.device) == (64, 2, "cpu") and callable(args.run)
    cfg = load_appliance(REPO / "configs/appliance.yaml")
    fixed = cfg.fluoroscope.model_copy(update={"abc": cfg.fluoroscope.abc.model_copy(update={"enabled": False})})
    small = dataclasses.replace(cfg, fluoroscope=at_resolution(fixed, 96, 96))   # one spectrum's tables
    assert run_save_bench(small, 32, 0.3, "cpu", repeats=1) == 0
    out = capsys.readouterr().out
    rows = {line[:38].strip(): line[38:].split() for line in out.splitlines()
            if line.startswith(("live alone", "save as before", "save paced"))}
    assert set(rows) == {"live alone", "save as before: 16 bands, share 1", "save paced: 64 bands, share 0.5"}
    assert len(rows["live alone"]) == 4 and all(len(v) == 6 for k, v in rows.items() if k != "live alone")
    assert all(float(v[4]) > 0 for k, v in rows.items() if k != "live alone")     # each save took some time


@pytest.mark.parametrize("shown", ["never", "a second ago", "while saving"])
def test_the_render_workers_save_waits_only_while_live_frames_are_shown(tmp_path, shown):
    """RenderWorker.native_image in 6 bands at share 0.5: the cast asks `cancelled` before each
    band, and the pacer asks it again after every slice it waits. With no frame shown, or the
    last one shown a second ago (more than LIVE_GAP_S), no live frame is coming: 6 asks, no
    wait. With a frame shown at each ask, the pacer waits after every band, at least one
    slice each: at least 2 asks per band."""
    from appliance.daemon.native_save import LIVE_GAP_S
    from appliance.daemon.render_worker import RenderWorker

    keeper = ProfileKeeper(REPO / "configs/appliance-demo.yaml", data_dir=tmp_path)
    cfg = keeper.current
    daemon = cfg.appliance.daemon.model_copy(update={"save_bands": 6, "save_device_share": 0.5})
    fixed = II.model_copy(update={"abc": II.abc.model_copy(update={"enabled": False})})   # one spectrum's tables
    keeper.current = dataclasses.replace(cfg, fluoroscope=at_resolution(fixed, 48, 48),
                                         appliance=cfg.appliance.model_copy(update={"daemon": daemon}))
    live = Renderer(at_resolution(fixed, 24, 24), Materials(), device="cpu")
    worker = RenderWorker(types.SimpleNamespace(renderer=live), keeper, poses=LatestValue(), phases=LatestValue(),
                          console_state=LatestValue(), saves=LatestValue(), shown=LatestValue(),
                          exposure_factor=LatestValue(), banners=list, on_first_frame=lambda: None)
    assert worker.native_image() is None                  # no live frame yet
    volume = box_volume((40, 40, 40), (2.0, 2.0, 2.0), (5, 5, 5), (34, 34, 34))[0]
    worker._request = (live.prepare(volume), acceptance.ap_pose(II.geometry.source_to_isocentre_mm),
                       View(noise=False, temporal="live"), None)
    if shown == "a second ago":
        worker.stats.shown_at.append(time.monotonic() - 4 * LIVE_GAP_S)
    asks = []

    def cancelled() -> bool:
        asks.append(time.monotonic())
        if shown == "while saving":
            worker.stats.shown_at.append(time.monotonic())
        return False
    image, native_fl = worker.native_image(cancelled)
    assert image.shape == (48, 48) and image.dtype == np.uint16 and native_fl.detector.columns == 48
    if shown == "while saving":
        assert len(asks) >= 2 * 6 - 1
    else:
        assert len(asks) == 6
