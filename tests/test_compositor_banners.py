"""Warning banners on the monitor: long messages wrap at spaces into lines that fit the field,
a word too long for a line is cut, nothing is lost or reordered, and each banner's box holds
its lines. Widths are measured with OpenCV's own text metrics, as the screen draws them."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from appliance.display.compositor import AMBER, FONT, Compositor, Overlay
from appliance.display.text import wrap_text

MESSAGE = ("camera lost: the webcam at usb-0000:00:14.0-2 stopped sending frames; check its cable "
           "and that no other program holds the device, then wait for it to come back")


def wrap(c: Compositor, text: str, max_w: int) -> list[str]:
    """The compositor's wrapping at its own text size (display/text.py)."""
    return wrap_text(text, max_w, c.scale, c.thickness)


def width(c: Compositor, text: str) -> int:
    return cv2.getTextSize(text, FONT, c.scale, c.thickness)[0][0]


@pytest.mark.parametrize("size", [(1280, 1024), (640, 512), (320, 256)])
def test_long_text_wraps_greedily_at_spaces_into_lines_that_fit(size):
    c = Compositor(*size)
    max_w = round(c.side * 0.9) - 2 * c.margin
    lines = wrap(c, MESSAGE, max_w)
    assert len(lines) >= 2
    assert " ".join(lines) == MESSAGE                              # every word, in order, none split
    assert all(width(c, line) <= max_w for line in lines), [(line, width(c, line)) for line in lines]
    for line, following in zip(lines, lines[1:]):
        # Greedy: the next line's first word would not have fitted on this one.
        assert width(c, f"{line} {following.split()[0]}") > max_w, (line, following)


def test_a_word_longer_than_a_line_is_cut_into_pieces_that_fit():
    c = Compositor(640, 512)
    max_w = 150
    word = "/dev/serial/by-id/usb-FTDI_FT232R_USB_UART_A50285BI-if00-port0"
    lines = wrap(c, f"pedal {word} gone", max_w)
    assert "".join(lines).replace(" ", "") == f"pedal{word}gone"
    assert lines[0] == "pedal" and lines[-1].endswith("gone")
    assert all(width(c, line) <= max_w for line in lines), lines
    pieces = [line for line in lines if line not in ("pedal",) and not line.endswith("gone")]
    assert len(pieces) >= 2 and all(len(p) >= 8 for p in pieces)
    # Wherever the line ends, each cut piece fits and is as long as fits (unless it is the shortest cut).
    for max_w in range(100, 420, 15):
        lines = wrap(c, word, max_w)
        assert "".join(lines) == word and all(width(c, line) <= max_w for line in lines), (max_w, lines)
        for piece, rest in zip(lines, lines[1:]):
            assert len(piece) == 8 or width(c, piece + rest[0]) > max_w, (max_w, piece)
    # Text exactly as wide as the line still fits on it, a word or a cut piece alike.
    assert wrap(c, "tracking lost", width(c, "tracking lost")) == ["tracking lost"]
    assert wrap(c, "ABCDEFGHIJ", width(c, "ABCDEFGHIJ")) == ["ABCDEFGHIJ"]
    # A piece is never cut shorter than 8 characters, even where 8 are wider than the line.
    assert wrap(c, "ABCDEFGHIJKLMNOPQRST", width(c, "ABC")) == ["ABCDEFGH", "IJKLMNOP", "QRST"]
    # A short text is one line; nothing at all is one empty line.
    assert wrap(c, "tracking lost", max_w) == ["tracking lost"]
    assert wrap(c, "", max_w) == [""]
    assert wrap(c, "   ", max_w) == [""]


def test_a_banner_box_holds_its_wrapped_lines_and_the_next_goes_below_it():
    c = Compositor(640, 512)
    frame = np.zeros((512, 640, 3), np.uint8)
    y_top = 100
    below = c._banner(frame, MESSAGE, y_top, AMBER, (0, 0, 0))
    amber = np.all(frame == AMBER, axis=2)
    rows = np.nonzero(amber.any(axis=1))[0]
    cols = np.nonzero(amber.any(axis=0))[0]
    assert rows.min() == y_top and below > rows.max()              # the next banner starts under this one
    assert below - rows.max() <= c.margin                          # and close under it
    # Centred across the screen, no wider than the image square.
    assert abs((cols.min() + cols.max()) / 2 - 320) <= 1 and cols.max() - cols.min() <= c.side * 0.9 + 1
    # As many text lines as the wrap gives: count the bands of black text inside the box.
    lines = wrap(c, MESSAGE, round(c.side * 0.9) - 2 * c.margin)
    box = frame[rows.min():rows.max() + 1, cols.min():cols.max() + 1]
    text_rows = (box.sum(axis=2) < 200).any(axis=1)
    bands = int(np.sum(text_rows[1:] & ~text_rows[:-1]) + text_rows[0])
    assert bands == len(lines), (bands, lines)
    # Drawn from the bottom: the box ends at y and the returned y is above it.
    frame[...] = 0
    above = c._banner(frame, "alarm", 400, AMBER, (0, 0, 0), from_bottom=True)
    rows = np.nonzero(np.all(frame == AMBER, axis=2).any(axis=1))[0]
    assert rows.max() == 400 and above < rows.min() and rows.min() - above <= c.margin


def test_warnings_stack_as_separate_banners_at_most_four():
    c = Compositor(640, 512)
    image = np.full((64, 64), 0.5, np.float32)
    few = c.compose(image, Overlay(warnings=["camera lost", "pedal unplugged"]), now=0.75)
    many = c.compose(image, Overlay(warnings=[f"warning {k}" for k in range(7)]), now=0.75)

    def banners(frame):
        rows = np.all(frame == AMBER, axis=2).any(axis=1)
        return int(np.sum(rows[1:] & ~rows[:-1]) + rows[0])

    assert banners(few) == 2 and banners(many) == 4                # the fourth stands for the rest
