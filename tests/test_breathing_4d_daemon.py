"""A 4D CT under the breathing keys, in the running appliance: the daemon's workers (synthetic
webcam, tracker, scripted keypad and pedal, console, phase worker, renderer, file framebuffer)
on a small 4D CT written to disk, its rate raised and its depth lowered from the keymap's keys.

Ground truth, worked by hand from the issue's contract and the case: the CT holds one 4 s breath
in 8 phases, a bone blob moved by A/2 (1 + sin(2 pi t / 4 s)) mm (end-expiration, offset 0, at
t = 3 s). The breath count runs at 15/min, then 18 and 21/min from the two faster presses (the
phase kept at each press); the CT's time is its end-expiration plus the count's fraction past
end-expiration times 4 s, between two phases blended linearly. After the two shallower presses
(and their 1 s ease) the depth is 0.5: end-expiration blended with the phase nearest the breath
at weight 0.5, so the blob's shadow moves half as far. Each rendered image's blob is read as the
centroid of what the blob adds to the image (a blend's centroid is the blend of the two blobs'
positions: the test's fluoroscope shows the log signal through a plain window, no lag, glare or
noise).
"""

import json
import math
import threading
import time

import numpy as np
import pytest
import SimpleITK as sitk
from appliance_setup import CASE_PLACEMENT, make_appliance
from ruamel.yaml import YAML
from test_screen_e2e import still_trajectory

from appliance.daemon.notify import Notifier
from appliance.daemon.pipeline import Appliance
from appliance.daemon.reload import ProfileKeeper

PERIOD_S, N_PHASES, A_MM, T_EE = 4.0, 8, 20.0, 3.0
RATE, STEP = 15.0, 3.0                 # the case's rate and the profile's default rate step (breaths/min)
FASTER = (5.0, 5.2)                    # console times of the two faster presses (s)
SHALLOWER = (10.0, 10.2)               # and of the two shallower ones
END_S = 15.0

CASE = """title: Breathing 4D CT
phases:
{phases}
at_end: loop
""" + CASE_PLACEMENT + """respiration:
  rate_per_min: {rate}
  rate_step_per_min: {step}
  ct_end_expiration_s: {t_ee}
"""

SCRIPT = [json.dumps({"t": 0.3, "hold": "pedal", "for_s": END_S - 0.3})]
SCRIPT += [json.dumps({"t": t, "tap": "KEY_F11", "tap_s": 0.02}) for t in FASTER]
SCRIPT += [json.dumps({"t": t, "tap": "KEY_KPCOMMA", "tap_s": 0.02}) for t in SHALLOWER]


def offset_mm(t_ct: float) -> float:
    """The blob's offset in the CT's phase at time t_ct of its breath."""
    return A_MM / 2.0 * (1.0 + math.sin(2.0 * math.pi * t_ct / PERIOD_S))


def write_phase(path, offset: float) -> None:
    """48^3 voxels of 3 mm: a water cylinder (r 65 mm) along z and a bone blob (Gaussian, sigma 3 mm,
    1500 HU at its centre) at x = offset - 4 mm: smooth, so its shadow's centroid is where it is
    whatever the voxel grid, small beside its travel, and in the middle of the field."""
    n, spacing = 48, 3.0
    c = (np.arange(n) - (n - 1) / 2) * spacing
    z, y, x = np.meshgrid(c, c, c, indexing="ij")
    hu = np.full((n, n, n), -1000.0)
    hu[x**2 + y**2 <= 65.0**2] = 0.0
    hu += 1500.0 * np.exp(-((x + 4.0 - offset) ** 2 + y**2 + z**2) / (2 * 3.0**2))
    image = sitk.GetImageFromArray(np.rint(hu).astype(np.int16))
    image.SetSpacing((spacing,) * 3)
    image.SetOrigin((float(c[0]),) * 3)
    sitk.WriteImage(image, str(path), True)


def cycles(t: float) -> float:
    """Breaths counted by hand: 15/min, one step faster at each faster press."""
    rate, last, c = RATE, 0.0, 0.0
    for press in FASTER:
        if t <= press:
            break
        c += rate / 60.0 * (press - last)
        rate, last = rate + STEP, press
    return c + rate / 60.0 * (t - last)


def expected_mm(t: float, depth: float) -> float:
    """The blob's offset shown at case time t (s) and breathing depth: the CT's time from the count,
    two phases blended (depth 1), or end-expiration blended with the nearest phase (depth below 1)."""
    t_ct = (T_EE + PERIOD_S * ((cycles(t) - 0.75) % 1.0)) % PERIOD_S
    dt = PERIOD_S / N_PHASES
    i = int(t_ct // dt)
    w = t_ct / dt - i
    a, b = offset_mm(i * dt), offset_mm(((i + 1) % N_PHASES) * dt)
    if depth >= 1.0:
        return (1.0 - w) * a + w * b
    return depth * (b if w >= 0.5 else a)


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("breathing4d")
    config = make_appliance(tmp, script=SCRIPT, render_px=64, clock_rate=2.0)
    still_trajectory(config)
    cases = config.parent / "cases"
    lines = []
    for k in range(N_PHASES):
        t = k * PERIOD_S / N_PHASES
        write_phase(cases / f"breath-{k}.mha", offset_mm(t))
        lines.append(f"  - {{volume: breath-{k}.mha, time_s: {t}}}")
    (cases / "breathing-4d.yaml").write_text(CASE.format(phases="\n".join(lines), rate=RATE, step=STEP, t_ee=T_EE))
    yaml = YAML(typ="rt")
    data = yaml.load(config.read_text())
    data["case"] = "cases/breathing-4d.yaml"
    with open(config, "w") as f:
        yaml.dump(data, f)
    fluoroscope = config.parent / data["fluoroscope"]
    profile = yaml.load(fluoroscope.read_text())
    profile["display"]["noise"] = False
    # The log signal through a plain window: what is shown is linear in the blended line integrals.
    profile["image"].update(recursive_weight=0.0, veiling_glare=0.0, display_knee=0.0, unsharp_amount=0.0)
    with open(fluoroscope, "w") as f:
        yaml.dump(profile, f)

    shown: list[tuple[float, np.ndarray]] = []

    def keep(frame):
        if frame.live and frame.image is not None and frame.t_case_s is not None:
            shown.append((frame.t_case_s, np.array(frame.image, dtype=np.float64)))

    app = Appliance(ProfileKeeper(config), Notifier({}), on_shown=keep)
    stop = threading.Event()
    runner = threading.Thread(target=app.run, kwargs={"until": stop.is_set, "signals": False})
    runner.start()
    try:
        deadline = time.monotonic() + 90
        while time.monotonic() < deadline and not (shown and shown[-1][0] > END_S - 0.2):
            time.sleep(0.1)
    finally:
        stop.set()
        runner.join(20)
    assert not runner.is_alive()
    return shown


def _depth(t: float) -> float | None:
    """The depth by hand, where it is not easing (None inside the shallower presses' ramps)."""
    if t < SHALLOWER[0]:
        return 1.0
    if t > SHALLOWER[1] + 1.0 + 0.05:
        return 0.5
    return None


def _centroids(shown):
    """The blob's shadow in each image (its centroid, pixels u, v, over what the blob adds to the
    cylinder: the darkest each pixel is over the run, the blob being elsewhere at the breath's
    extremes), and the hand's offsets (mm)."""
    stack = np.array([image for _, image in shown])
    background = stack.min(axis=0)
    rows, cols = background.shape
    v, u = np.mgrid[0:rows, 0:cols]
    out, expect = [], []
    for t, image in shown:
        depth = _depth(t)
        if depth is None:
            continue
        d = image - background
        out.append([(d * u).sum() / d.sum(), (d * v).sum() / d.sum()])
        expect.append(expected_mm(t, depth))
    return np.array(out), np.array(expect)


def _fit(centroids, expect):
    """Least squares centroids = c0 + offset * B (the pose is still: one linear map); residual rms in mm."""
    X = np.c_[np.ones_like(expect), expect]
    coef, *_ = np.linalg.lstsq(X, centroids, rcond=None)
    residual = centroids - X @ coef
    scale = np.linalg.norm(coef[1])
    return float(np.sqrt((residual ** 2).sum(axis=1).mean()) / scale), coef


def test_the_rendered_blob_follows_the_4d_ct_under_the_rate_and_depth_keys(frames):
    centroids, expect = _centroids(frames)
    times = np.array([t for t, _ in frames if _depth(t) is not None])
    # Frames over the whole run: each regime (15/min, 21/min, depth 0.5) seen over most of a breath.
    for lo, hi in ((0.5, FASTER[0]), (FASTER[1], SHALLOWER[0]), (SHALLOWER[1] + 1.1, END_S)):
        inside = (times > lo) & (times < hi)
        assert inside.sum() >= 8, f"only {inside.sum()} images between {lo} and {hi} s"
    rms_mm, coef = _fit(centroids, expect)
    assert rms_mm < 0.02 * A_MM
    # The shallow breaths move the blob half as far as the CT's own: the extremes after the ease.
    late = times > SHALLOWER[1] + 1.1
    shown_range = np.ptp((centroids[late] - coef[0]) @ coef[1] / (coef[1] @ coef[1]))
    assert shown_range <= 0.5 * A_MM * 1.05
    assert shown_range >= 0.5 * A_MM * 0.6        # most of a shallow breath was imaged


def test_a_timeline_without_the_keys_does_not_fit_the_images(frames):
    """The check can fail: the same images against the CT played at its own rate and depth."""
    centroids, _ = _centroids(frames)
    ignored = np.array([expected_mm_plain(t) for t, _ in frames if _depth(t) is not None])
    rms_mm, _ = _fit(centroids, ignored)
    assert rms_mm > 0.15 * A_MM


def expected_mm_plain(t: float) -> float:
    t_ct = t % PERIOD_S
    dt = PERIOD_S / N_PHASES
    i = int(t_ct // dt)
    w = t_ct / dt - i
    return (1.0 - w) * offset_mm(i * dt) + w * offset_mm(((i + 1) % N_PHASES) * dt)
