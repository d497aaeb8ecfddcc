"""`fluorosim bench ledger`: what the console and the ledger cost per displayed frame.

Drives the console through a scripted session at 30 frames/s of console time (pulsed
fluoroscopy at 15/s half the time, key presses now and then), commits each frame's events
as one ledger transaction (WAL, synchronous=FULL: one fsync per frame with events), then
times recovery of an interrupted session and a full chain verification. The same session is
then recorded again with each event authenticated: by a key in this process, and through the
seal helper over its Unix socket (as on an installed appliance), each commit also moving the
anchor; their medians are given beside the unsealed one, measured in the same run. Prints
medians and 95th percentiles; writes only scratch files under --out (or a temporary folder).
"""

from __future__ import annotations

import argparse
import random
import statistics
import tempfile
import time
from pathlib import Path

from drivers.input_event import InputEvent

from .seal import Seal


def _percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))]


def _sealed_commit_s(scratch: Path, frames: int, how: str) -> list[float]:
    """Commit times per frame with events of the same session, each event sealed `how`."""
    import socket
    import threading

    from .seal import HelperSeal, KeySeal, make_key, serve

    folder = scratch / how
    folder.mkdir()
    make_key(folder / "ledger.key")
    key_seal = KeySeal(folder / "ledger.key", folder / "anchor.json")
    seal: Seal = key_seal
    listener = None
    if how == "helper":
        listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        listener.bind(str(folder / "seal.sock"))
        listener.listen(4)
        threading.Thread(target=serve, args=(listener, key_seal, folder / "ledger.sqlite"), daemon=True).start()
        seal = HelperSeal(folder / "seal.sock")
    try:
        return _session(folder / "ledger.sqlite", frames, seal)[1]
    finally:
        if listener is not None:
            listener.close()


def _session(path: Path, frames: int, seal: Seal | None) -> tuple[list[float], list[float], list[int]]:
    """(console tick s, ledger commit s per frame with events, events per such frame) of the
    bench's session, recorded into `path` with `seal` (None: hash chain only)."""
    from ..config import FluoroscopeProfile, KeymapProfile, load_profile
    from ..console.state import Console
    from .ledger import Ledger

    root = Path(__file__).resolve().parents[2] / "configs"
    fl = load_profile(root / "fluoroscopes/generic-ii-carm.yaml", FluoroscopeProfile)
    km = load_profile(root / "keymaps/usb-numeric-keypad.yaml", KeymapProfile)
    rng = random.Random(1)
    console = Console(fl, km, t0=0.0)
    tick_s: list[float] = []
    record_s: list[float] = []
    events_per_frame: list[int] = []
    with Ledger(path, seal=seal) as ledger:
        ledger.start_session("bench", "bench", fl.name, t_wall=time.time(), t_monotonic=0.0)
        console.handle(InputEvent(0.0, "keypad", "mode_next", True))
        pedal = False
        for frame in range(1, frames + 1):
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
    return tick_s, record_s, events_per_frame


def run_bench(args: argparse.Namespace) -> int:
    from .ledger import Ledger, open_readonly, verify

    with tempfile.TemporaryDirectory(dir=args.out) as scratch:
        path = Path(scratch) / "ledger.sqlite"
        tick_s, record_s, events_per_frame = _session(path, args.frames, None)
        t0 = time.perf_counter()
        with Ledger(path, seal=None) as ledger:      # the session above was never ended: this recovers it
            recovered = ledger.recovered
        t_recover = time.perf_counter() - t0
        conn = open_readonly(path)
        t0 = time.perf_counter()
        report = verify(conn)
        t_verify = time.perf_counter() - t0
        conn.close()
        sealed = {how: _sealed_commit_s(Path(scratch), args.frames, how) for how in ("key", "helper")}
    print(f"frames: {args.frames} (30/s of console time), frames with events: {len(record_s)}, "
          f"events per such frame: median {statistics.median(events_per_frame):.0f}")
    print(f"console tick + snapshot: median {statistics.median(tick_s) * 1e6:.1f} us, "
          f"p95 {_percentile(tick_s, 0.95) * 1e6:.1f} us")
    print(f"ledger commit per frame (WAL, synchronous=FULL): median {statistics.median(record_s) * 1e3:.2f} ms, "
          f"p95 {_percentile(record_s, 0.95) * 1e3:.2f} ms")
    base = statistics.median(record_s)
    for how, times in sealed.items():
        what = "key in this process" if how == "key" else "seal helper over its socket"
        print(f"ledger commit per frame, sealed ({what}, anchor moved each commit): median "
              f"{statistics.median(times) * 1e3:.2f} ms, p95 {_percentile(times, 0.95) * 1e3:.2f} ms, "
              f"{statistics.median(times) / base:.1f}x the unsealed median")
    print(f"recovery of an interrupted session: {t_recover * 1e3:.1f} ms (sessions {recovered}); "
          f"chain verify: {report.events} events in {t_verify * 1e3:.1f} ms ({'intact' if report.ok else 'BROKEN'})")
    return 0


def register_bench(benches: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    b = benches.add_parser("ledger", help="console tick and ledger commit cost per frame",
                           description=__doc__.splitlines()[0])
    b.add_argument("--frames", type=int, default=1800, help="frames to simulate (default 1800 = 60 s at 30/s)")
    b.add_argument("--out", default=None, metavar="DIR", help="where the scratch ledger goes (default: a temporary folder)")
    b.set_defaults(run=run_bench)
