"""The screen drawn into a reused buffer, and a 32 bpp frame packed straight into screen memory,
against the fresh path and against the pixel layout worked by hand."""

from __future__ import annotations

import numpy as np
import pytest

from appliance.display.compositor import Compositor, Overlay
from drivers.pixel_format import PixelFormat


@pytest.mark.parametrize("width, height", [(320, 256), (256, 320), (256, 108), (108, 256)])
def test_a_reused_screen_shows_exactly_what_a_fresh_one_does(width, height):
    """On a landscape screen the image square has borders left and right, on a portrait one
    above and below: whatever the busy frame drew there is cleared for the next. A 21:9 screen
    (256 x 108, as 2560 x 1080) has borders wider than half the square, and so has its portrait."""
    comp = Compositor(width, height)
    rng = np.random.default_rng(4)
    busy = Overlay(live=True, case="Adult chest", operator="A. Trainee", fluoroscope="Generic", alarm=True,
                   alarm_since=0.0, saved_flash=True, warnings=["camera lost", "pedal unplugged"], cue="task met: PA",
                   collimation_mm=(120.0, 90.0), fps=14.0)
    plain = Overlay(live=False, case="Other case", operator="B", fluoroscope="Generic")
    screen = np.full((height, width, 3), 77, np.uint8)      # whatever was there before
    comp.compose(rng.random((64, 64), dtype=np.float32), busy, 0.1, out=screen)
    image = rng.random((48, 64), dtype=np.float32)           # letterboxed: the square's own black bars
    got = comp.compose(image, plain, 0.2, out=screen)
    assert got is screen
    assert np.array_equal(got, comp.compose(image, plain, 0.2))
    assert np.array_equal(comp.compose(None, plain, 0.3, out=screen), comp.compose(None, plain, 0.3))
    with pytest.raises(ValueError, match=rf"out must be \({height}, {width}, 3\) uint8"):
        comp.compose(image, plain, 0.2, out=np.zeros((height, width), np.uint8))
    with pytest.raises(ValueError, match=rf"out must be \({height}, {width}, 3\) uint8"):
        comp.compose(image, plain, 0.2, out=np.zeros((height, width, 3), np.float32))


@pytest.mark.parametrize("pad", [0, 24])
def test_32_bpp_packs_straight_into_screen_memory_as_blue_green_red_padding(pad):
    rng = np.random.default_rng(5)
    rgb = rng.integers(0, 256, (30, 40, 3), dtype=np.uint8)
    memory = np.zeros((30, 40 * 4 + 2 * pad), np.uint8)     # pad: a stride longer than the row
    out = memory[:, pad:pad + 160]
    PixelFormat.standard(32).pack(rgb, out)
    px = out.reshape(30, 40, 4)
    # The standard 32 bpp mode: red at bit 16, green at 8, blue at 0, padding 0xFF; little-endian bytes.
    assert np.array_equal(px[..., 0], rgb[..., 2]) and np.array_equal(px[..., 1], rgb[..., 1])
    assert np.array_equal(px[..., 2], rgb[..., 0]) and np.all(px[..., 3] == 255)
    assert not memory[:, :pad].any() and not memory[:, pad + 160:].any()
