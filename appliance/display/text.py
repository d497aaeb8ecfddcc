"""Text on the monitor: how the figures read (fluoroscopy time, dose), and how a line of
text is measured, wrapped and drawn legibly over the image.

The compositor decides what goes where; this module only knows fonts and pixels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from ..console.readout import minutes_and_tenths

FONT = cv2.FONT_HERSHEY_SIMPLEX
FONT_BOLD = cv2.FONT_HERSHEY_DUPLEX

#: An RGB colour, or one grey level where text is drawn into a single-channel mask.
Color = tuple[int, int, int] | int

WHITE = (255, 255, 255)
GREY = (170, 170, 170)
BLACK = (0, 0, 0)
YELLOW = (255, 214, 0)
AMBER = (255, 170, 0)
RED = (220, 0, 0)
GREEN = (0, 200, 80)

#: A superscript (the 2 of cm2) is drawn at this fraction of its line's font scale.
SUP_SCALE = 0.6
#: Lines shorter than this many characters are never cut inside a word when wrapped.
MIN_CUT_CHARS = 8


def fluoro_time_clock(seconds: float) -> str:
    """Fluoroscopy time as mm:ss, whole seconds counted (minutes go past 59: 100:00)."""
    whole = int(math.floor(max(seconds, 0.0) + 1e-9))
    return f"{whole // 60:02d}:{whole % 60:02d}"


def fluoro_time_minutes(seconds: float) -> str:
    """Fluoroscopy time in minutes and completed tenths, as clinical units display it: 2.6 min
    (the console's count of tenths, with the unit)."""
    return f"{minutes_and_tenths(seconds)} min"


def dose_number(value: float) -> str:
    """A dose figure with three significant digits up to 1000, whole numbers beyond."""
    value = max(value, 0.0)
    if value < 1:
        return f"{value:.3f}"
    if value < 10:
        return f"{value:.2f}"
    if value < 1000:
        return f"{value:.1f}" if value < 100 else f"{value:.0f}"
    return f"{value:.0f}"


def text_size(text: str, font: int, scale: float, thickness: int, sup: str = "") -> tuple[int, int, int]:
    """Width, height above the baseline and depth below it (pixels), superscript included."""
    (w, h), base = cv2.getTextSize(text, font, scale, thickness)
    if sup:
        (sw, sh), _ = cv2.getTextSize(sup, font, scale * SUP_SCALE, thickness)
        w += sw + thickness
        h = max(h, round(h * 0.5) + sh)
    return w, h, base


@dataclass
class TextLine:
    """One line of text laid out: baseline origin, size and the box it covers (x0, y0, x1, y1)."""

    text: str
    org: tuple[int, int]
    scale: float
    color: Color
    font: int
    thickness: int
    sup: str = ""      # a superscript after the text (the 2 of cm2)

    def size(self) -> tuple[int, int, int]:
        """Width, height above the baseline and depth below it (pixels), superscript included."""
        return text_size(self.text, self.font, self.scale, self.thickness, self.sup)

    @property
    def box(self) -> tuple[int, int, int, int]:
        w, h, base = self.size()
        pad = self.thickness + 1
        return (self.org[0] - pad, self.org[1] - h - pad, self.org[0] + w + pad, self.org[1] + base + pad)


def _outline_thickness(thickness: int) -> int:
    return thickness + 2 * max(1, thickness // 2 + 1)


def draw_text(frame: np.ndarray, t: TextLine, outline_color: Color = BLACK) -> None:
    """Draw `t` with a dark outline, which keeps text legible where it crosses the image."""
    cv2.putText(frame, t.text, t.org, t.font, t.scale, outline_color, _outline_thickness(t.thickness), cv2.LINE_AA)
    cv2.putText(frame, t.text, t.org, t.font, t.scale, t.color, t.thickness, cv2.LINE_AA)
    draw_sup(frame, t, outline_color)


def draw_sup(frame: np.ndarray, t: TextLine, outline_color: Color | None = None) -> None:
    """Draw the superscript of `t` (if any) after its text, outlined unless `outline_color` is None."""
    if not t.sup:
        return
    (w, h), _ = cv2.getTextSize(t.text, t.font, t.scale, t.thickness)
    org = (t.org[0] + w, t.org[1] - round(h * 0.4))
    scale = t.scale * SUP_SCALE
    if outline_color is not None:
        cv2.putText(frame, t.sup, org, t.font, scale, outline_color, _outline_thickness(t.thickness), cv2.LINE_AA)
    cv2.putText(frame, t.sup, org, t.font, scale, t.color, t.thickness, cv2.LINE_AA)


def wrap_text(text: str, max_w: int, scale: float, thickness: int, font: int = FONT) -> list[str]:
    """Break `text` at spaces into lines no wider than `max_w` pixels (a single long word is cut)."""

    def width(s: str) -> int:
        return int(cv2.getTextSize(s, font, scale, thickness)[0][0])

    lines: list[str] = []
    current = ""
    for word in text.split():
        candidate = f"{current} {word}" if current else word
        if current and width(candidate) > max_w:
            lines.append(current)
            candidate = word
        while width(candidate) > max_w and len(candidate) > MIN_CUT_CHARS:
            cut = max(MIN_CUT_CHARS, len(candidate) * max_w // width(candidate))
            # The estimate assumes letters of average width: move it to as much as fits.
            while cut > MIN_CUT_CHARS and width(candidate[:cut]) > max_w:
                cut -= 1
            while cut < len(candidate) and width(candidate[:cut + 1]) <= max_w:
                cut += 1
            lines.append(candidate[:cut])
            candidate = candidate[cut:]
        current = candidate
    if current:
        lines.append(current)
    return lines or [""]
