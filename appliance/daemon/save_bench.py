"""`fluorosim bench save`: what a saved image's native re-render costs the live view.

The live view is rendered in a loop, as the render worker renders it (the live matrix, the
recursive filter live), on the built-in child at the bladder; the save runs in a thread of
its own, as the records worker runs it, through native_save.native_frame. Three conditions,
interleaved and repeated so that the machine's load falls on all of them: the live view
alone, during a save as the appliance made it before pacing (16 bands back to back), and
during a save paced as the profile says (daemon.save_bands, daemon.save_device_share).
Reported: the live frame period (median, longest), the rate as a fraction of the rate alone
measured next to it, the save's duration, and the longest gap between its calls of the
records worker's callback (how late a dose event arriving during the save is written).
"""

from __future__ import annotations

import os
import statistics
import threading
import time

from ..config import ApplianceConfig
from ..config.appliance import Daemon
from .native_save import LIVE_GAP_S, native_frame


def _live_loop(renderer, request, stop: threading.Event, periods: list[float], last: list[float]) -> None:
    volume, T, view, blend = request
    t = time.monotonic()
    while not stop.is_set():
        renderer.render(volume, T, view, blend=blend)
        now = time.monotonic()
        periods.append(now - t)
        last[0] = t = now


def _measure(renderer, request, native_fl, daemon: Daemon | None, seconds: float, warm: int = 3) -> dict[str, float]:
    """Live frame periods for `seconds` alone (daemon None) or while one save runs."""
    stop, last = threading.Event(), [time.monotonic()]
    periods: list[float] = []
    live = threading.Thread(target=_live_loop, args=(renderer, request, stop, periods, last), daemon=True)
    live.start()
    while len(periods) < warm:
        time.sleep(0.01)
    del periods[:]
    out: dict[str, float] = {}
    if daemon is None:
        time.sleep(seconds)
    else:
        asked: list[float] = []

        def callback() -> bool:            # the records worker's: it beats and records events here
            asked.append(time.monotonic())
            return False
        t0 = time.monotonic()
        _, pacer = native_frame(renderer, request, native_fl, daemon, True, callback,
                                lambda: time.monotonic() - last[0] < LIVE_GAP_S)
        out["save_s"] = time.monotonic() - t0
        gaps = [b - a for a, b in zip([t0, *asked], [*asked, time.monotonic()])]
        out["longest_gap_s"] = max(gaps)
    stop.set()
    live.join()
    out["period_s"] = statistics.median(periods) if periods else float("nan")
    out["longest_s"] = max(periods) if periods else float("nan")
    out["frames"] = float(len(periods))
    return out


def run_save_bench(cfg: ApplianceConfig, matrix: int, seconds: float, device: str, repeats: int = 3) -> int:
    from ..config.case import CaseProfile
    from ..config.commands import default_config_dir
    from ..config.loading import load_profile
    from ..daemon.parts import is_cpu
    from ..patient import builtin
    from ..patient.volume import Volume
    from ..xray.acceptance import ap_pose
    from ..xray.renderer import Renderer, View, at_resolution

    fl = cfg.fluoroscope
    case = load_profile(default_config_dir() / "cases" / "child-torso-vcug.yaml", CaseProfile)
    renderer = Renderer(at_resolution(fl, matrix, matrix), case.materials, case.contrast, device=device)
    b = builtin.Builder()
    child = Volume(hu=b.phase(builtin.PhaseSpec(12.0, 3, 0.0)), T_ct_from_voxel=builtin.grid().T_ct_from_voxel,
                   source="built-in child, bladder full")
    request = (renderer.prepare(child), ap_pose(fl.geometry.source_to_isocentre_mm, (0.0, 0.0, -140.0)),
               View(zoom=1, noise=True, temporal="live"), None)
    cpu = is_cpu(renderer)
    print(f"fluorosim bench save: {fl.name}, live {matrix}x{matrix}, saved {fl.detector.columns}x{fl.detector.rows}; "
          f"built-in child at the bladder; {renderer.device.name.strip()}; {os.cpu_count()} CPU(s), "
          f"load average {os.getloadavg()[0]:.1f}", flush=True)
    if not cpu:
        print("not a CPU device: the native re-render is cast whole, and is not paced")
    before = cfg.appliance.daemon.model_copy(update={"save_bands": 16, "save_device_share": 1.0})
    after = cfg.appliance.daemon
    native_frame(renderer, request, fl, after, cpu)           # builds the native matrix's rays and tables
    conditions: list[tuple[str, Daemon | None]] = [
        ("live alone", None), ("save as before: 16 bands, share 1", before),
        (f"save paced: {after.save_bands} bands, share {after.save_device_share:g}", after)]
    runs: dict[str, list[dict[str, float]]] = {label: [] for label, _ in conditions}
    for _ in range(repeats):                  # interleaved, so a change in the machine's load hits all three
        for label, daemon in conditions:
            runs[label].append(_measure(renderer, request, fl, daemon, seconds))
    alone = runs["live alone"]

    def median(label: str, key: str) -> float:
        return statistics.median(m[key] for m in runs[label])
    print(f"medians of {repeats} interleaved runs each")
    print(f"{'':38} {'live ms':>8} {'max ms':>7} {'fps':>6} {'of alone':>8} {'save s':>7} {'gap ms':>7}")
    for label, daemon in conditions:
        # The rate during a save against the rate alone measured next to it, run by run.
        share = statistics.median(a["period_s"] / m["period_s"] for a, m in zip(alone, runs[label]))
        period = median(label, "period_s")
        save = f"{median(label, 'save_s'):7.2f}" if daemon is not None else f"{'':7}"
        gap = f"{1000 * median(label, 'longest_gap_s'):7.0f}" if daemon is not None else f"{'':7}"
        print(f"{label:38} {1000 * period:8.1f} {1000 * median(label, 'longest_s'):7.0f} {1 / period:6.1f} "
              f"{share:8.2f} {save} {gap}")
    print("live ms: median live frame period while the save ran (alone: over the same time); max ms: the longest; "
          "of alone: the live frame rate over the rate alone in the run next to it; gap ms: the longest the "
          "records worker's callback went unasked during the save, which is how long a dose event arriving "
          "meanwhile waits for the ledger (before the callback wrote events, it waited for the whole save)")
    return 0
