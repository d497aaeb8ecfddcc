"""`fluorosim run`, `fluorosim demo`, `fluorosim bench e2e` and `fluorosim bench save`."""

from __future__ import annotations

import logging
from pathlib import Path

from ..command_options import add_command, non_negative_number, positive_number
from ..config.commands import default_config_dir


def _default(name: str) -> str:
    return str(default_config_dir() / name)


def run_run(args) -> int:
    # Imported here so `fluorosim --help` does not load OpenCL, OpenCV and the rest.
    from .logqueue import start_logging
    from .notify import Notifier
    from .pipeline import Appliance
    from .reload import ProfileKeeper

    keeper = ProfileKeeper(Path(args.config))
    daemon = keeper.current.appliance.daemon
    logs = start_logging(keeper.current.data_dir / "logs", level=logging.DEBUG if args.verbose else logging.INFO,
                         max_mb=daemon.log_max_mb, backups=daemon.log_backups)
    try:
        app = Appliance(keeper, Notifier())
        return app.run()
    finally:
        logs.stop()


def run_demo(args) -> int:
    from .demo import run_demo as demo
    return demo(Path(args.config), case=Path(args.case) if args.case else None, seconds=args.seconds, ct=args.ct)


def run_bench_e2e(args) -> int:
    from .bench import run_e2e
    return run_e2e(Path(args.config), minutes=args.minutes, out=Path(args.out) if args.out else None,
                   case=Path(args.case) if args.case else None, ct=args.ct, still_s=args.still)


def run_bench_save(args) -> int:
    from ..config.loading import load_appliance
    from .save_bench import run_save_bench
    return run_save_bench(load_appliance(args.config or _default("appliance.yaml")), args.matrix, args.seconds, args.device,
                          args.repeats)


def register(commands, benches) -> None:
    p = add_command(commands, "run", run_run, "run the appliance (what the systemd service starts)",
                    "Run the appliance: camera, tracking, rendering, console and ledger under a "
                    "supervisor that speaks sd_notify. SIGHUP reloads the profiles (a bad edit "
                    "keeps the last good ones and says why on screen); SIGTERM ends the session "
                    "and exits within 2 s.")
    p.add_argument("--config", default=_default("appliance.yaml"), metavar="PATH",
                   help="appliance profile (default: configs/appliance.yaml)")
    p.add_argument("--verbose", action="store_true", help="log debug messages too")

    d = add_command(commands, "demo", run_demo, "show the whole appliance working on the built-in patient",
                    "Run the real appliance with a synthetic camera moving the intensifier over "
                    "the box, a scripted keypad and pedal session under an accelerated clock, and "
                    "a file framebuffer; then write snapshots, a contact sheet and the dose logs "
                    "under the demo's data_dir and print a summary.")
    d.add_argument("--case", metavar="PATH", help="case profile to use instead of the built-in patient "
                                                 "(configs/cases/X.yaml, which may point at your own CT)")
    d.add_argument("--config", default=_default("appliance-demo.yaml"), metavar="PATH",
                   help="the demo's appliance profile (default: configs/appliance-demo.yaml)")
    d.add_argument("--ct", choices=("chest",), help="the real-size adult chest CT (512x512x136, drawn once into the "
                                                   "data folder's cache) instead of the built-in patient, for the "
                                                   "frame rate at that size; the path and the exercise are the child's, "
                                                   "so the views are no chest examination's and no exercise is offered")
    d.add_argument("--seconds", type=float, default=None, metavar="S",
                   help="stop after this many wall-clock seconds (default: when the scripted session ends)")

    b = add_command(benches, "e2e", run_bench_e2e, "frames per second on screen, motion-to-photon latency, memory growth",
                    "Run the appliance with the synthetic camera, fluoroscopy held on and the file "
                    "framebuffer; report frames per second on screen, camera-frame-to-framebuffer "
                    "latency (median, p99) and resident memory growth.")
    b.add_argument("--config", default=_default("appliance-bench.yaml"), metavar="PATH",
                   help="appliance profile to run (default: configs/appliance-bench.yaml)")
    b.add_argument("--minutes", type=positive_number, default=0.5, help="how long to run (min; default 0.5; 10 for the memory figure)")
    b.add_argument("--out", metavar="DIR", help="data_dir for the run (default: the profile's, var/bench)")
    b.add_argument("--case", metavar="CASE.yaml", help="run this case instead of the profile's")
    b.add_argument("--ct", choices=("chest", "chest-breathing"),
                   help="run the real-size adult chest CT (512x512x136, drawn once into the data folder's cache), "
                        "held or breathing (15 breaths a minute, 15 mm of diaphragm)")
    b.add_argument("--still", type=non_negative_number, metavar="SECONDS",
                   help="a cheap camera: the synthetic webcam's frame at this trajectory time, looped from a file")

    s = add_command(benches, "save", run_bench_save, "the live frame rate while a saved image is re-rendered",
                    "Render the live view in a loop on the built-in child, and meanwhile a saved image at "
                    "the detector's native matrix, as the appliance does on a CPU device: report the median "
                    "live frame period alone, during a save with its bands back to back and during one paced "
                    "as the profile's daemon.save_bands and daemon.save_device_share say, each save's "
                    "duration and the longest a dose event waits for the ledger meanwhile.")
    s.add_argument("--config", metavar="PATH", help="appliance profile (default: configs/appliance.yaml)")
    s.add_argument("--matrix", type=int, default=256, help="live matrix (px; default 256, a CPU appliance's)")
    s.add_argument("--seconds", type=float, default=3.0, help="how long the live view runs alone (s; default 3)")
    s.add_argument("--device", choices=("auto", "cpu", "gpu"), default="cpu", help="OpenCL device (default cpu)")
    s.add_argument("--repeats", type=int, default=3, help="runs of each condition, interleaved (default 3)")
