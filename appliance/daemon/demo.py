"""`fluorosim demo`: the real appliance on the built-in patient, with no hardware at all.

The demo profile (configs/appliance-demo.yaml) names a synthetic camera moving the
intensifier over the box on a scripted path (with the +-90 degree rolls), a scripted
keypad and pedal session under an accelerated clock, and a file framebuffer. The demo
builds or loads the patient, runs the same supervised daemon `fluorosim run` runs,
snapshots key moments from the framebuffer, writes a contact sheet, exports the dose
logs, and prints a summary. Everything it writes goes under the profile's data_dir.
"""

from __future__ import annotations

import logging
import math
import time
from pathlib import Path

from drivers.scripted_input import ScriptedInput

from ..errors import FluorosimError
from .frame_stats import fps_text
from .logqueue import start_logging
from .notify import Notifier
from .reload import ProfileKeeper
from .snapshots import Snapshotter, contact_sheet, key_moments, read_png, write_png

#: Wall-clock seconds the demo keeps running after the script's last event, so the last
#: images and the alarm reset reach the screen and the ledger.
TAIL_S = 2.0
#: Seconds between progress lines while the appliance runs.
PROGRESS_EVERY_S = 5.0


def _say(message: str) -> None:
    print(message, flush=True)


def shown(path: Path) -> str:
    """A path as a person reads it: relative to the working directory when inside it."""
    p = Path(path).resolve()
    try:
        return str(p.relative_to(Path.cwd().resolve()))
    except ValueError:
        return str(p)


def build_patient(cfg, say=_say) -> int:
    """Build the built-in patient (first run; cached afterwards) or read a case's CT phases,
    with progress lines; returns the number of phases."""
    from .parts import patient_phases

    t0 = time.monotonic()
    if cfg.case.builtin:
        say(f"[1/4] built-in patient '{cfg.case.builtin}' (cached under {shown(cfg.data_dir / 'cache')})")
        from ..patient.builtin import distinct_volumes

        phases = patient_phases(cfg, progress=lambda message: say(f"      {message}"))
        volume = phases[0][1]()
        nx, ny, nz = volume.shape_xyz
        say(f"      {len(phases)} phases ({distinct_volumes()} distinct volumes) of {nx}x{ny}x{nz} voxels "
            f"ready in {time.monotonic() - t0:.1f} s")
        r = cfg.case.respiration
        if r is not None:
            say(f"      breathing under the model at {r.rate_per_min:g}/min: each VCUG stage's end-expiration "
                f"volume moved to {r.depth_states} depth states when the appliance starts")
        return len(phases)
    say(f"[1/4] case '{cfg.case.title}' ({shown(cfg.case_path)}): reading its CT")
    phases = patient_phases(cfg)
    for i, (t_s, loader) in enumerate(phases, 1):
        t1 = time.monotonic()
        nx, ny, nz = loader().shape_xyz
        say(f"      phase {i}/{len(phases)} at {t_s:g} s: {nx}x{ny}x{nz} voxels ({time.monotonic() - t1:.1f} s)")
    say(f"      ready in {time.monotonic() - t0:.1f} s")
    return len(phases)


def run_demo(config_path: Path, *, case: Path | None = None, seconds: float | None = None,
             ct: str | None = None) -> int:
    """`ct` "chest": the real-size adult chest CT of `bench e2e --ct chest` instead of `case`."""
    from .pipeline import Appliance

    if ct == "chest":
        from .bench import adult_chest_case

        case = adult_chest_case(ProfileKeeper(config_path).current.data_dir)
    keeper = ProfileKeeper(config_path, case=case)
    cfg = keeper.current
    devices = cfg.appliance.devices
    if devices.display.target != "file":
        raise FluorosimError(f"{config_path}: devices.display.target must be 'file' for the demo")
    if seconds is None and devices.keypad.source != "scripted":
        raise FluorosimError(f"{config_path}: devices.keypad.source must be 'scripted' for the demo to know when "
                             "its session ends (or give --seconds)")
    cfg.data_dir.mkdir(parents=True, exist_ok=True)
    logs = start_logging(cfg.data_dir / "logs", console_level=logging.WARNING,
                         max_mb=cfg.appliance.daemon.log_max_mb, backups=cfg.appliance.daemon.log_backups)
    try:
        build_patient(cfg)
        snap_dir = cfg.data_dir / "snapshots"
        snap_dir.mkdir(parents=True, exist_ok=True)
        for old in snap_dir.glob("*.png"):
            old.unlink()
        # The PNGs are written beside the render worker, not in its frame (snapshots.py).
        snapper = Snapshotter(snap_dir, key_moments(), reserve_mb=cfg.appliance.daemon.records_reserve_mb,
                              background=True)
        _say("[2/4] starting the appliance: phases onto the OpenCL device, kernels built, camera started")
        t_open = time.monotonic()
        app = Appliance(keeper, Notifier(), on_shown=snapper)
        _say(f"      ready in {time.monotonic() - t_open:.1f} s; rendering on {app.parts.renderer_device}")
        rate = app.clock.rate
        screen = shown(cfg.data_dir / devices.display.path) if devices.display.path else devices.display.target
        session_s: float | None = None
        wall_s = seconds if seconds is not None else 0.0
        if seconds is None:
            # The session lasts as long as its script, on the appliance clock (which a paced clock
            # may slow down on a busy machine), plus a short tail.
            keypad = app.parts.keypad
            session_s = (keypad.duration_s if isinstance(keypad, ScriptedInput) else 0.0) + TAIL_S * rate
            paced = f", paced: at most {app.clock.pace_s:g} s ahead of the screen" if app.clock.pace_s else ""
            _say(f"      running the {session_s:.0f} s session (appliance clock x{rate:g}{paced}; screen: {screen})")
        else:
            _say(f"      running for {seconds:.0f} s (appliance clock x{rate:g}; screen: {screen})")
        t_run = time.monotonic()
        next_line = [t_run + PROGRESS_EVERY_S]

        def until() -> bool:
            now = time.monotonic()
            if now >= next_line[0]:
                next_line[0] += PROGRESS_EVERY_S
                _say("      " + progress_line(app, now - t_run))
            if session_s is not None:
                return app.clock() - app.parts.t0 >= session_s
            return now - t_run >= wall_s

        app.run(until=until)
        run_s = time.monotonic() - t_run
        snapper.flush()

        _say("[3/4] contact sheet and dose logs")
        captions = snapper.captions()
        shots = sorted(snapper.taken.items(), key=lambda kv: kv[1].name)
        sheet_path = None
        if shots:
            sheet_path = write_png(snap_dir / "contact-sheet.png",
                                   contact_sheet([(captions.get(n, n), read_png(p)) for n, p in shots]))
        exports = export_logs(app, cfg.data_dir / "exports")
        report = teaching_report(app, cfg.data_dir / "reports")

        _say("[4/4] summary")
        from .breath_pair import pair_lines

        pair = pair_lines(cfg, app.parts.renderer.fluoroscope, snapper.kept)
        for line in summary_lines(app, run_s, shots, sheet_path, exports, snapper.missing()) + pair + report_lines(app, report):
            _say("      " + line)
        return 0
    finally:
        logs.stop()


def progress_line(app, elapsed_s: float) -> str:
    state, _ = app.console_state.get()
    stats = app.stats
    fluoro = _mmss(state.fluoro_time_s) if state is not None else "--:--"
    banners = app.supervisor.banners()
    return (f"{elapsed_s:5.1f} s  fluoro {fluoro}  frames {stats.frames}  {fps_text(stats.fps(time.monotonic()))}"
            + (f"  [{'; '.join(banners)}]" if banners else ""))


def _mmss(seconds: float) -> str:
    m, s = divmod(int(round(seconds)), 60)
    return f"{m:02d}:{s:02d}"


def export_logs(app, out_dir: Path) -> dict[str, list[Path]]:
    """This session's dose log as CSV, JSON and DICOM RDSR: what `fluorosim logs export` writes."""
    from ..records import export
    from ..records.ledger import open_readonly

    conn = open_readonly(app.ledger.path)
    try:
        row = conn.execute("SELECT started_wall FROM sessions WHERE id = ?", (app.session_id,)).fetchone()
        if row is None:
            return {}
        since = row[0]
        until = math.nextafter(since, math.inf)  # exactly this session
        folder = out_dir / f"session-{app.session_id:06d}"
        paths = {}
        for fmt in export.FORMATS:
            written, notes = export.export(conn, since, until, fmt, folder)
            for note in notes:
                logging.getLogger(__name__).warning("export %s: %s", fmt, note)
            paths[fmt] = written
        return paths
    finally:
        conn.close()


def teaching_report(app, out_dir: Path) -> Path | None:
    """This session's instructor report: what `fluorosim report session N` writes."""
    from ..records.ledger import open_readonly
    from ..teaching.report import write_session_report

    if app.session_id is None:
        return None
    conn = open_readonly(app.ledger.path)
    try:
        return write_session_report(conn, app.session_id, out_dir, images_dir=app.config.data_dir / "images")
    finally:
        conn.close()


def report_lines(app, report: Path | None) -> list[str]:
    progress = app.teaching.progress
    lines = []
    if progress is not None:
        lines.append(f"exercise:           {progress.exercise.title}: {progress.met_count()}/{len(progress.tasks)} tasks met, "
                     f"{app.teaching.exposures} exposures")
    if report is not None:
        lines.append(f"teaching report:    {shown(report)}")
    return lines


def summary_lines(app, run_s: float, shots, sheet_path, exports, missing: list[str]) -> list[str]:
    s = app.stats.summary()
    state, _ = app.console_state.get()
    lines = [
        f"frames on screen:   {int(s['frames'])} live in {run_s:.1f} s",
        f"frame rate:         {s['fps']:.1f} fps over the session; {s['fps_exposing']:.1f} fps while exposing in a "
        "continuous mode (pulsed modes show their pulse rate)",
        f"latency:            median {s['latency_median_ms']:.0f} ms, p99 {s['latency_p99_ms']:.0f} ms "
        "(camera frame to framebuffer write)",
    ]
    if state is not None:
        lines += [
            f"fluoroscopy time:   {_mmss(state.fluoro_time_s)} (simulated)",
            f"reference air kerma: {state.air_kerma_mgy:.2f} mGy",
            f"DAP:                {state.dap_gy_cm2:.3f} Gy.cm2",
        ]
    lines.append(f"snapshots:          {len(shots)}" + (f" (not seen on screen: {', '.join(missing)})" if missing else ""))
    lines += [f"  {shown(p)}" for _, p in shots]
    if sheet_path is not None:
        lines.append(f"contact sheet:      {shown(sheet_path)}")
    lines.append(f"saved images:       {len(app.saved)}")
    for png, dcm in app.saved:
        lines.append(f"  {shown(dcm)}  ({png.name})")
    for fmt, paths in exports.items():
        lines.append(f"dose log ({fmt}):{' ' * (9 - len(fmt))}" + ", ".join(shown(p) for p in paths))
    return lines
