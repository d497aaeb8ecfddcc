"""The LIVE / HOLD marker read back from the composed screen, not from the layout's own list."""

from __future__ import annotations

import numpy as np
from test_compositor import plain_overlay as overlay  # the overlay of a quiet screen, one place

from appliance.display.compositor import Compositor

W, H = 1280, 1024


def corner(frame: np.ndarray) -> np.ndarray:
    """The bottom-right corner outside the image circle, where the marker sits."""
    return frame[H * 7 // 8:, W * 7 // 8:].astype(int)


def white_glyph_box(frame: np.ndarray) -> tuple[int, int, int]:
    """(count, width, height) of the near-white pixels in the corner."""
    c = corner(frame)
    white = (c > 225).all(axis=-1)
    if not white.any():
        return 0, 0, 0
    ys, xs = np.nonzero(white)
    return int(white.sum()), int(xs.max() - xs.min() + 1), int(ys.max() - ys.min() + 1)


def test_hold_marker_is_white_text_four_glyphs_wide():
    comp = Compositor(W, H)
    black = np.zeros((64, 64), np.float32)
    count, width, height = white_glyph_box(comp.compose(black, overlay(live=False), now=0.0))
    # Four capital letters side by side: a word, wider than tall, with real strokes.
    assert count > 300, "no HOLD text in the corner"
    assert 2.0 < width / height < 6.0, (width, height)


def test_live_marker_replaces_hold_and_neither_is_shown_twice():
    comp = Compositor(W, H)
    black = np.zeros((64, 64), np.float32)
    live = corner(comp.compose(black, overlay(live=True), now=0.0))
    yellow = (live[..., 0] > 230) & (live[..., 1] > 190) & (live[..., 1] < 235) & (live[..., 2] < 40)
    assert yellow.sum() > 500, "LIVE is a yellow block"
    assert white_glyph_box(comp.compose(black, overlay(live=True), now=0.0))[0] == 0, "no white HOLD while live"
    # The black letters of LIVE sit inside the yellow block: its bounding box holds dark pixels.
    ys, xs = np.nonzero(yellow)
    block = live[ys.min():ys.max() + 1, xs.min():xs.max() + 1]
    dark = (block < 60).all(axis=-1)
    assert dark.sum() > 150, "the word on the LIVE block"
