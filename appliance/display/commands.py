"""`fluorosim screenshot OUT.png` and `fluorosim bench display`."""

from __future__ import annotations

import statistics
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from drivers.framebuffer import FakeFramebuffer, FileDisplay, FramebufferDisplay
from drivers.pixel_format import PixelFormat

from ..atomic_file import write_atomic
from ..config import ApplianceProfile, load_profile
from ..errors import FluorosimError
from .compositor import Compositor, Overlay
from .target import open_target

#: Where `--config` is looked for when not given: a checkout's configs/, then the installed appliance.
DEFAULT_CONFIGS = (Path("configs/appliance.yaml"), Path("/etc/fluorosim/appliance.yaml"))


def default_config() -> Path:
    for candidate in DEFAULT_CONFIGS:
        if candidate.is_file():
            return candidate
    raise FluorosimError("no appliance profile found (configs/appliance.yaml or /etc/fluorosim/appliance.yaml); "
                         "give one with --config")


def write_png(path: Path, rgb: np.ndarray) -> None:
    ok, png = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    if not ok:
        raise FluorosimError(f"{path}: could not encode the PNG")
    write_atomic(path, png.tobytes())


def run_screenshot(args) -> int:
    out = Path(args.out)
    if out.suffix.lower() != ".png":
        raise FluorosimError(f"{out}: the screenshot is written as PNG; give a name ending in .png")
    config = Path(args.config) if args.config else default_config()
    if not config.is_file():
        raise FluorosimError(f"{config}: no such appliance profile")
    profile = load_profile(config, ApplianceProfile)
    with open_target(config, profile, read_only=True) as display:
        rgb = display.read_back()
    write_png(out, rgb)
    print(f"{out}: {rgb.shape[1]}x{rgb.shape[0]} screen of {profile.devices.display.target}")
    return 0


# ---------------------------------------------------------------------- benchmark

def bench_overlay() -> Overlay:
    """Every overlay element at once: the most text a frame carries."""
    return Overlay(live=True, zoom=2, fov_mm=230.0, collimation_mm=(160.0, 120.0), fluoro_time_s=317.4,
                   air_kerma_mgy=12.3, dap_gy_cm2=0.876, mode="pulsed-15", alarm=True, saved_flash=True,
                   invert=True, breath_hold=True, case="Child torso VCUG", operator="trainee",
                   fluoroscope="Generic image-intensifier C-arm", warnings=["tracking lost", "pedal unplugged"], fps=14.9)


def bench_image(n: int) -> np.ndarray:
    yy, xx = np.mgrid[0:n, 0:n]
    return (0.5 + 0.4 * np.sin(xx / 23.0) * np.cos(yy / 37.0)).astype(np.float32)


class Timing:
    """Median and fastest of repeated calls (ms); the fastest shows the cost on an idle machine."""

    def __init__(self, fn, frames: int):
        fn(0)   # the first call builds caches
        times = []
        for i in range(frames):
            t0 = time.perf_counter()
            fn(i)
            times.append(time.perf_counter() - t0)
        self.median_ms = 1000.0 * statistics.median(times)
        self.min_ms = 1000.0 * min(times)

    def __str__(self) -> str:
        return f"{self.median_ms:.2f} ms (fastest {self.min_ms:.2f})"


def run_bench(args) -> int:
    frames = args.frames
    image = bench_image(args.image_size)
    overlay = bench_overlay()
    out = Path(args.out) if args.out else None
    if out:
        out.mkdir(parents=True, exist_ok=True)
    if frames < 1 or args.image_size < 8:
        raise FluorosimError("--frames must be at least 1 and --image-size at least 8")
    print(f"display benchmark: {frames} frames each, {args.image_size}x{args.image_size} image; "
          f"median (fastest) per frame")
    for width, height in ((1920, 1080), (1280, 1024)):
        comp = Compositor(width, height)
        timing = Timing(lambda i, comp=comp: comp.compose(image, overlay, now=i * 0.04), frames)
        screen = np.zeros((height, width, 3), np.uint8)
        reused = Timing(lambda i, comp=comp, screen=screen: comp.compose(image, overlay, now=i * 0.04, out=screen), frames)
        print(f"  compose {width}x{height}: {timing}; into one reused screen (as the render worker does) {reused}")
        if out:
            write_png(out / f"compose-{width}x{height}.png", comp.compose(image, overlay, now=0.1))
    frame = Compositor(1920, 1080).compose(image, overlay, now=0.1)
    with tempfile.TemporaryDirectory(prefix="fluorosim-bench-display-") as tmp:
        for bpp in (16, 24, 32):
            with FileDisplay(str(Path(tmp) / f"screen{bpp}.raw"), 1920, 1080, bpp) as display:
                show = Timing(lambda i: display.show(frame), frames)
                back = Timing(lambda i: display.read_back(), max(frames // 10, 3))
            node = FakeFramebuffer(str(Path(tmp) / f"fb{bpp}"), 1920, 1080, PixelFormat.standard(bpp), pages=2)
            with FramebufferDisplay(node) as display:
                flip = Timing(lambda i: display.show(frame), frames)
            print(f"  {bpp} bpp 1920x1080: show with one copy {show}; show with pan flip {flip}; read back {back}")
    return 0


def register(commands, benches) -> None:
    p = commands.add_parser("screenshot", help="save what is on the screen as a PNG",
                            description="Read the configured display (framebuffer or screen file) back and write it "
                                        "to OUT as a PNG, without disturbing the running appliance.")
    p.add_argument("out", metavar="OUT.png")
    p.add_argument("--config", metavar="PATH",
                   help="appliance profile (default: configs/appliance.yaml, else /etc/fluorosim/appliance.yaml)")
    p.set_defaults(run=run_screenshot)

    b = benches.add_parser("display", help="compositor and framebuffer write times",
                           description="Median time to compose a full screen at 1920x1080 and 1280x1024, and to put "
                                       "a 1920x1080 frame on a file and a double-buffered framebuffer at 16, 24 and 32 bpp.")
    b.add_argument("--frames", type=int, default=200, help="frames timed per figure (default 200)")
    b.add_argument("--image-size", type=int, default=1024, help="rendered image side (pixels, default 1024)")
    b.add_argument("--out", metavar="DIR", help="also write the composed screens as PNGs into DIR")
    b.set_defaults(run=run_bench)
