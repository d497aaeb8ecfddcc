"""`fluorosim bench ledger`: what the console and the ledger cost per displayed frame.

Drives the console through a scripted session at 30 frames/s of console time (pulsed
fluoroscopy at 15/s half the time, key presses now and then), commits each frame's events
as one ledger transaction (WAL, synchronous=FULL: one fsync per frame with events), then
times recovery of an interrupted session and a full chain verification. Prints medians and
95th percentiles; writes only a scratch ledger under --out (or a temporary folder).
"""

from __future__ import annotations

import argparse
import random
import statistics
import tempfile
import time
from pathlib import Path

from drivers.input_event import InputEvent


def _percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))]


def run_bench(args: argparse.Namespace) -> int:
    from ..config import FluoroscopeProfile, KeymapProfile, load_profile
    from ..console.state import Console
    from .ledger import Ledger, open_readonly, verify

    root = Path(__file__).resolve().parents[2] / "configs"
    fl = load_profile(root / "fluoroscopes/generic-ii-carm.yaml", FluoroscopeProfile)
    km = load_profile(root / "keymaps/usb-numeric-keypad.yaml", KeymapProfile)
    with tempfile.TemporaryDirectory(dir=args.out) as scratch:
        path = Path(scratch) / "ledger.sqlite"
        rng = random.Random(1)
        console = Console(fl, km, t0=0.0)
        tick_s, record_s, events_per_frame = [], [], []
        with Ledger(path) as ledger:
            ledger.start_session("bench", "bench", fl.name, t_wall=time.time(), t_monotonic=0.0)
            console.handle(InputEvent(0.0, "keypad", "mode_next", True))
            pedal = False
            for frame in range(1, args.frames + 1):
                t = frame / 30.0
                events = []
                if frame % 90 == 0:
                    pedal = not pedal
                    events += console.handle(InputEvent(t, "pedal", "pedal", pedal))
                if rng.random() < 0.01:
                    events += console.handle(InputEvent(t, "keypad", rng.choice(["KEY_KP7", "KEY_KP9", "KEY_KP2", "KEY_KP1"]), True))
                t0 = time.perf_counter()
                events += console.tick(t)
                console.snapshot()
                t1 = time.perf_counter()
                ledger.record(events)
                t2 = time.perf_counter()
                tick_s.append(t1 - t0)
                if events:
                    record_s.append(t2 - t1)
                    events_per_frame.append(len(events))
        t0 = time.perf_counter()
        with Ledger(path) as ledger:      # the session above was never ended: this recovers it
            recovered = ledger.recovered
        t_recover = time.perf_counter() - t0
        conn = open_readonly(path)
        t0 = time.perf_counter()
        report = verify(conn)
        t_verify = time.perf_counter() - t0
        conn.close()
    print(f"frames: {args.frames} (30/s of console time), frames with events: {len(record_s)}, "
          f"events per such frame: median {statistics.median(events_per_frame):.0f}")
    print(f"console tick + snapshot: median {statistics.median(tick_s) * 1e6:.1f} us, "
          f"p95 {_percentile(tick_s, 0.95) * 1e6:.1f} us")
    print(f"ledger commit per frame (WAL, synchronous=FULL): median {statistics.median(record_s) * 1e3:.2f} ms, "
          f"p95 {_percentile(record_s, 0.95) * 1e3:.2f} ms")
    print(f"recovery of an interrupted session: {t_recover * 1e3:.1f} ms (sessions {recovered}); "
          f"chain verify: {report.events} events in {t_verify * 1e3:.1f} ms ({'intact' if report.ok else 'BROKEN'})")
    return 0


def register_bench(benches: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    b = benches.add_parser("ledger", help="console tick and ledger commit cost per frame",
                           description=__doc__.splitlines()[0])
    b.add_argument("--frames", type=int, default=1800, help="frames to simulate (default 1800 = 60 s at 30/s)")
    b.add_argument("--out", default=None, metavar="DIR", help="where the scratch ledger goes (default: a temporary folder)")
    b.set_defaults(run=run_bench)
