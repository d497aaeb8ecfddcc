"""`fluorosim bench e2e`: the whole appliance measured end to end on this machine.

The appliance runs as `fluorosim run` runs it, with the synthetic camera, fluoroscopy held
on by the bench's input script, and the file framebuffer. Reported: live frames per
second on screen, motion-to-photon latency (camera frame timestamp to framebuffer
write; median and 99th percentile), and resident memory growth from the end of warm-up
to the end of the run.
"""

from __future__ import annotations

import logging
import os
import time
from pathlib import Path

import cv2
import numpy as np
import psutil

from drivers.camera import CameraSource

from ..tracking.trajectory import Trajectory
from .demo import shown
from .logqueue import start_logging
from .notify import Notifier
from .reload import ProfileKeeper
from .stage_times import breakdown_text

#: Frames and memory of the first part of a run are not counted: kernel compilation,
#: patient loading and allocator warm-up are start-up costs, not steady state (fraction of the run).
WARMUP_FRACTION = 0.2
#: Warm-up lasts at least this long (s).
WARMUP_MIN_S = 5.0


def adult_chest_case(data_dir: Path, breathing: bool = False) -> Path:
    """The case profile of the real-size adult chest CT (512 x 512 x 136), written under
    data_dir/cache on the first run and reused afterwards; with `breathing`, the profile that
    makes the same CT breathe (adult-chest-breathing.yaml)."""
    from ..patient.adult_chest import write_adult_chest, write_profiles

    folder = data_dir / "cache" / "adult-chest"
    profile = folder / ("adult-chest-breathing.yaml" if breathing else "adult-chest.yaml")
    if not (folder / "adult-chest.mha").exists():
        print(f"drawing the adult chest CT into {shown(folder)} (once)", flush=True)
        write_adult_chest(folder)
    elif not profile.exists():                 # a cache drawn before the breathing profile was
        write_profiles(folder / "adult-chest.mha")
    return profile


class StillCamera(CameraSource):
    """The bench's cheap camera: one frame, drawn once, published again at `fps` (the C-arm at
    rest, at the cost of a real webcam's driver: next to nothing)."""

    def __init__(self, image: np.ndarray, fps: float):
        super().__init__()
        self.image, self.fps = image, fps

    def _run(self) -> None:
        period = 1.0 / self.fps
        next_t = time.monotonic()
        while not self._stop.is_set():
            self._publish(self.image, time.monotonic())
            self._set_state("ok")
            next_t += period
            self._stop.wait(max(0.0, next_t - time.monotonic()))


def hold_camera_still(app, t_s: float) -> str:
    """Replace the synthetic webcam by the cheap StillCamera showing its frame at trajectory
    time `t_s`, at the same rate. Returns a label for the report."""
    cam = app.parts.camera
    image, _ = cam.render_at(t_s)
    still = StillCamera(image, cam.fps)
    app.parts.camera = app.capture.camera = still
    return f"a still frame (the synthetic webcam's at {t_s:g} s, drawn once) at {cam.fps:g} fps"


def synthetic_camera_cost(app, frames: int = 7) -> str:
    """What the synthetic webcam and the tracker cost per camera frame (median cpu ms), measured
    before the run on the webcam's own scene; "" for another camera."""
    from ..tracking.sources import tracker_for

    cam = app.parts.camera
    if not hasattr(cam, "render_at"):
        return ""
    tracker = tracker_for(app.config)          # a tracker of its own: the appliance's keeps its state
    cam.render_at(4.5)                  # its first frame also draws the sensor's noise pool: not counted
    draw, track = [], []
    threads = cv2.getNumThreads()
    # This thread's CPU time, OpenCV kept on it: the appliance's other threads (the patient's
    # loading) run meanwhile, and process time would count them too.
    cv2.setNumThreads(1)
    try:
        for i in range(frames):
            c0 = time.thread_time()
            image, _ = cam.render_at(5.0 + 0.5 * i)
            c1 = time.thread_time()
            tracker.track(image, 5.0 + 0.5 * i)
            draw.append(c1 - c0)
            track.append(time.thread_time() - c1)
    finally:
        cv2.setNumThreads(threads)
    fps = cam.fps
    d, t = 1000 * float(np.median(draw)), 1000 * float(np.median(track))
    return (f"drawing a synthetic webcam frame {d:.0f} cpu ms, tracking it {t:.0f} cpu ms; at {fps:g} fps the "
            f"drawing alone takes {d * fps / 10:.0f} % of one core, which a real webcam does not")


#: Longest the bench waits for a case's phases (or breathing states) before it measures (s).
PREPARE_TIMEOUT_S = 600.0


def prepare_patient(timeline) -> str:
    """Wait until every phase (or breathing state) of the case is prepared, as it is some tens
    of seconds after a case is loaded, so the measured minute is the appliance's steady state
    rather than its loader's; returns how long that took, for the report."""
    t0 = time.monotonic()
    every = timeline.wait_ready(PREPARE_TIMEOUT_S, all_phases=True)
    took = time.monotonic() - t0
    n = timeline.ready_count
    volumes = f"{n} volume{'' if n == 1 else 's'} (phases or breathing states)"
    return (f"{volumes} in {took:.0f} s, before the warm-up" if every
            else f"only {volumes} after {took:.0f} s; the rest are prepared while it is measured")


def rests_after(renderer, since: float) -> list[float]:
    """The "full matrix after rest" delays (s, ProgressiveRenderer.refined_after_s) of the
    full-matrix images ready at or after `since` (s, its clock; `refined_at`): the warm-up's
    first rest, cast while the kernels and ray tables were still being made, is not one of the
    measured span's."""
    delays, ready = getattr(renderer, "refined_after_s", []), getattr(renderer, "refined_at", [])
    return [d for d, t in zip(delays, ready) if t >= since]


def native_after_stops(camera, refined_at: list[float], since: float, until: float) -> str | None:
    """The "native matrix within 500 ms of the C-arm coming to rest" figure, timed from when the
    synthetic webcam's path stands still (its keyframes, `Trajectory.still_spans`) to the first
    full-matrix image after it: the pose filter's lag behind the stop, the settle time and the
    full matrix's cast all included. Stops wholly between `since` and `until` (s, the clock the
    path and the renderer share, the wall's at clock rate 1) are counted. None without such a path."""
    trajectory, t0 = getattr(camera, "trajectory", None), getattr(camera, "t0", None)
    if not isinstance(trajectory, Trajectory) or t0 is None:
        return None
    period = trajectory.duration if trajectory.loop and trajectory.duration > 0 else np.inf
    delays, missed = [], 0
    for start, end in trajectory.still_spans():
        n = 0
        while t0 + end + n * period <= until:
            a, b = t0 + start + n * period, t0 + end + n * period
            n += 1
            if a < since:
                continue
            first = [r for r in refined_at if a <= r < b]
            if first:
                delays.append(first[0] - a)
            else:
                missed += 1
            if not np.isfinite(period):
                break
    if not delays and not missed:
        return None
    text = (f"median {np.median(delays) * 1000:.0f} ms, max {max(delays) * 1000:.0f} ms" if delays
            else "never")
    stops = len(delays) + missed
    return (f"{text} after the camera's path stood still ({stops} stop{'' if stops == 1 else 's'}"
            f"{f', {missed} not refined before it moved on' if missed else ''})")


def held_casts_text(renderer, since: float) -> str | None:
    """What a held view cast within its frames after `since` (s, the renderer's clock): how many
    frames, their time to render, and the casts of upcoming phases begun beside the live frames
    (ProgressiveRenderer.held_casts, prefetched_at). None for a renderer without them."""
    held = getattr(renderer, "held_casts", None)
    if held is None:
        return None
    took = [s for t, s in held if t >= since]
    within = (f"{len(took)} frames cast a phase within themselves (median {np.median(took) * 1000:.0f} ms, "
              f"max {max(took) * 1000:.0f} ms to render)" if took else "no frame cast a phase within itself")
    ahead = sum(t >= since for t in renderer.prefetched_at)
    return f"{within}; {ahead} casts of coming phases begun beside the live frames"


def run_e2e(config_path: Path, *, minutes: float = 0.5, out: Path | None = None, case: Path | None = None,
            ct: str | None = None, still_s: float | None = None) -> int:
    from .pipeline import Appliance

    if ct in ("chest", "chest-breathing"):
        base = ProfileKeeper(config_path, data_dir=Path(out) if out else None).current.data_dir
        case = adult_chest_case(base, breathing=ct == "chest-breathing")
    keeper = ProfileKeeper(config_path, case=case, data_dir=Path(out) if out else None)
    data_dir = keeper.current.data_dir
    logs = start_logging(data_dir / "logs", console_level=logging.WARNING)
    try:
        app = Appliance(keeper, Notifier())
        prepared = prepare_patient(app.parts.timeline)
        camera_cost = synthetic_camera_cost(app)
        camera = None if still_s is None else hold_camera_still(app, still_s)
        duration = minutes * 60.0
        warmup = max(WARMUP_MIN_S, WARMUP_FRACTION * duration)
        process = psutil.Process()
        rss: list[tuple[float, int]] = []
        cfg = keeper.current
        matrix = app.parts.renderer.shape[1]     # the profile's, or the CPU's (parts.rendered_fluoroscope)
        ladder = getattr(app.parts.renderer, "control", None)
        moving = "/".join(str(n) for n in ladder.ladder) if ladder is not None and ladder.ladder else None
        camera = camera or f"{cfg.appliance.devices.camera.source} at {cfg.appliance.devices.camera.fps:g} fps"
        print(f"bench e2e: {config_path}, case {cfg.case.title}, {duration:.0f} s measured after {warmup:.0f} s "
              f"warm-up; renderer on {app.parts.renderer_device}, {matrix} px matrix"
              f"{f' ({moving} px while moving)' if moving else ''}; camera {camera}; "
              f"load average {os.getloadavg()[0]:.1f}; data in {shown(data_dir)}", flush=True)
        print(f"patient prepared:       {prepared}", flush=True)
        t0 = time.monotonic()
        next_sample = [t0]

        cpu_at: dict[str, float] = {}

        def until() -> bool:
            now = time.monotonic()
            if now >= next_sample[0]:
                rss.append((now - t0, process.memory_info().rss))
                next_sample[0] += 1.0
            if "start" not in cpu_at and now - t0 >= warmup:
                cpu_at["start"] = time.process_time()
                cpu_at["camera_start"] = app.parts.camera.frames_captured
            done = now - t0 >= duration + warmup
            if done:
                cpu_at["end"] = time.process_time()
                cpu_at["camera_end"] = app.parts.camera.frames_captured
            return done

        app.run(until=until)
        t_shown = np.array(app.stats.shown_at) - t0
        lat = np.array(app.stats.latencies_s)
        steady = t_shown >= warmup
        n = int(steady.sum())
        span = duration
        fps = n / span if span > 0 else float("nan")
        after = [r for t, r in rss if t >= warmup]
        growth = (after[-1] - after[0]) / after[0] * 100 if len(after) >= 2 else float("nan")
        print(f"frames on screen:       {n} live in {span:.0f} s ({app.stats.frames} with the warm-up)")
        print(f"frames per second:      {fps:.1f}")
        if n and "start" in cpu_at and "end" in cpu_at:
            # What the appliance itself spent, whatever else the machine ran: on an otherwise idle
            # machine with N cores, the frame rate approaches N * 1000 / (cpu ms per frame).
            cpu_ms = 1000 * (cpu_at["end"] - cpu_at["start"]) / n
            print(f"CPU per live frame:     {cpu_ms:.0f} cpu ms (all threads; load average {os.getloadavg()[0]:.1f} "
                  f"on {os.cpu_count()} CPUs)")
        if n:
            print(f"motion-to-photon:       median {np.median(lat[steady]) * 1000:.0f} ms, "
                  f"p99 {np.percentile(lat[steady], 99) * 1000:.0f} ms")
        stages = app.render.stages.summary(since=t0 + warmup)
        if stages:
            print(f"latency by stage:       {breakdown_text(stages)}")
        if after:
            print(f"resident memory:        {after[0] / 2**20:.0f} MiB -> {after[-1] / 2**20:.0f} MiB "
                  f"({growth:+.1f} % over {rss[-1][0] - warmup:.0f} s)")
        renderer = app.parts.renderer
        refined = rests_after(renderer, t0 + warmup)
        if refined:
            print(f"full matrix after rest:  median {np.median(refined) * 1000:.0f} ms, max {max(refined) * 1000:.0f} ms "
                  f"after the pose came to rest ({len(refined)} times after the warm-up)")
        per_matrix = getattr(renderer, "moving_frames", None)
        if per_matrix is not None and not per_matrix:
            # The moving matrix is the native one (a GPU's profile, say): no frame waits for a refinement.
            print("native matrix after stop: every frame at the native matrix (none cast smaller while moving)")
        elif cfg.appliance.daemon.clock_rate == 1:
            end = time.monotonic()
            stops = native_after_stops(app.parts.camera, getattr(renderer, "refined_at", []), t0 + warmup, end)
            if stops:
                print(f"native matrix after stop: {stops}")
            interim = getattr(renderer, "interim", None)
            if interim is not None:
                stops = native_after_stops(app.parts.camera, renderer.interim_at, t0 + warmup, end)
                if stops:
                    print(f"rest matrix after stop:   {stops} ({interim.shape[1]} px, shown until the full matrix's "
                          f"cast is done)")
        if per_matrix:
            steps = renderer.control.steps
            print("moving frames:          " + ", ".join(f"{per_matrix[n]} at {n} px" for n in sorted(per_matrix, reverse=True))
                  + f"; {len(steps)} matrix steps" + (f" ({' '.join(f'{a}->{b}' for a, b in steps[:12])}"
                                                       f"{' ...' if len(steps) > 12 else ''})" if steps else ""))
        slabs = getattr(renderer, "slabs", None)
        if slabs is not None:
            print(f"slabs:                  {renderer.slab_casts} moving casts through slabs; {slabs.made} slab copies made, "
                  f"{slabs.nbytes / 2**20:.0f} MiB held at the end")
        counts = renderer.cache().counts if hasattr(renderer, "cache") else None
        if counts is not None:
            print(f"projection cache:       {counts.frames} full-matrix frames, {counts.casts} phase casts, "
                  f"{counts.hits} phases reused")
        held = held_casts_text(renderer, t0 + warmup)
        if held:
            print(f"held view:              {held}")
        if camera_cost:
            print(f"camera cost:            {camera_cost}")
        if "camera_end" in cpu_at:
            delivered = (cpu_at["camera_end"] - cpu_at["camera_start"]) / span
            nice = getattr(app.parts.camera, "thread_nice", None)
            print(f"camera frames:          {delivered:.1f} per second delivered of {cfg.appliance.devices.camera.fps:g} asked"
                  + (f" (drawing thread at nice {nice:g})" if nice is not None else ""))
        dropped = app.poses.dropped
        print(f"stale poses skipped:    {dropped} (the renderer always draws the newest)")
        undrawn = getattr(app.parts.camera, "frames_skipped", 0)
        print(f"frames not tracked:     {app.capture.skipped} (a newer frame came before the renderer wanted a pose)"
              + (f"; {undrawn} not drawn by the synthetic webcam" if undrawn else ""))
        return 0
    finally:
        logs.stop()
