"""Text on the monitor: how the figures read (fluoroscopy time, dose), and how a line of
text is measured, wrapped and drawn legibly over the image.

The compositor decides what goes where; this module only knows fonts and pixels.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any, cast

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


def outline_border(thickness: int) -> int:
    """Width of the dark outline round text drawn `thickness` px thick (pixels each side)."""
    return max(1, thickness // 2 + 1)


def _disc(radius: int) -> np.ndarray:
    """A disc of `radius` px as a structuring element: the outline is the same width every way."""
    r = np.arange(-radius, radius + 1)
    return ((r[:, None] ** 2 + r[None, :] ** 2) <= radius * radius).astype(np.uint8)


def _put(mask: np.ndarray, t: TextLine, origin: tuple[int, int]) -> None:
    """The coverage (0-255) of `t` and its superscript, drawn into `mask` whose pixel (0, 0)
    is the screen's pixel `origin`."""
    ox, oy = origin
    cv2.putText(mask, t.text, (t.org[0] - ox, t.org[1] - oy), t.font, t.scale, 255, t.thickness, cv2.LINE_AA)
    if t.sup:
        (w, h), _ = cv2.getTextSize(t.text, t.font, t.scale, t.thickness)
        org = (t.org[0] + w - ox, t.org[1] - round(h * 0.4) - oy)
        cv2.putText(mask, t.sup, org, t.font, t.scale * SUP_SCALE, 255, t.thickness, cv2.LINE_AA)


def _blend_layers(coverage: np.ndarray, color: Color, rgb: bool) -> tuple[np.ndarray, np.ndarray]:
    """What a blend of `color` at `coverage` keeps of the image (255 - coverage) and adds
    (coverage x colour / 255), in the frame's channels: they depend only on the line, so a
    line that reads the same from frame to frame is blended with one multiply and one add."""
    inverse = cv2.bitwise_not(coverage)                        # 255 - coverage
    if rgb:
        coverage, inverse = cv2.cvtColor(coverage, cv2.COLOR_GRAY2RGB), cv2.cvtColor(inverse, cv2.COLOR_GRAY2RGB)
    scalar = (*color, 0) if isinstance(color, tuple) else (color, 0, 0, 0)
    # OpenCV takes a colour as a Scalar here. Its type stubs have typed that argument differently
    # from release to release (arrays only, then Scalars too), so the call is typed loosely: the
    # type check passes with whichever OpenCV a fresh set-up installs.
    paint = cast(Any, cv2.multiply)(coverage, scalar, scale=1 / 255)
    inverse.flags.writeable = paint.flags.writeable = False
    return inverse, paint


def _apply(roi: np.ndarray, inverse: np.ndarray, paint: np.ndarray) -> None:
    keep = cv2.multiply(roi, inverse, scale=1 / 255)
    cv2.add(keep, paint, dst=roi)


def draw_text(frame: np.ndarray, t: TextLine, outline_color: Color = BLACK) -> None:
    """Draw `t` with a dark outline, which keeps text legible where it crosses the image.

    The outline is the text's own coverage dilated by a disc of outline_border(thickness) px,
    not the text drawn again with a thicker stroke: OpenCV draws Hershey text no bolder than
    about 2 px whatever the thickness asked, and widens the letters' advance with it, so a
    thicker stroke lay under the text on big screens and drifted off it along the line."""
    drawn = _layers(t.text, t.org, t.scale, t.font, t.thickness, t.sup, frame.shape[:2], frame.ndim == 3,
                    t.color, outline_color)
    if drawn is None:
        return
    x0, y0, layers = drawn
    h, w = layers[0][0].shape[:2]
    roi = frame[y0:y0 + h, x0:x0 + w]
    for inverse, paint in layers:           # the outline, then the text over it
        _apply(roi, inverse, paint)


@functools.lru_cache(maxsize=128)
def _layers(text: str, org: tuple[int, int], scale: float, font: int, thickness: int, sup: str,
            shape: tuple[int, ...], rgb: bool, color: Color, outline_color: Color
            ) -> tuple[int, int, tuple[tuple[np.ndarray, np.ndarray], ...]] | None:
    """Where a line goes and its blend layers (outline, then text): this runs for every line of
    text on every frame, and most lines read the same for many frames."""
    drawn = _coverages(text, org, scale, font, thickness, sup, shape)
    if drawn is None:
        return None
    x0, y0, core, outline = drawn
    return x0, y0, (_blend_layers(outline, outline_color, rgb), _blend_layers(core, color, rgb))


@functools.lru_cache(maxsize=128)
def _coverages(text: str, org: tuple[int, int], scale: float, font: int, thickness: int, sup: str,
               shape: tuple[int, ...]) -> tuple[int, int, np.ndarray, np.ndarray] | None:
    """Where a line of text goes on a screen of `shape` and its coverages (0-255) there: its
    own and its outline's. Kept for the lines that read the same from frame to frame."""
    t = TextLine(text, org, scale, 255, font, thickness, sup)
    border = outline_border(thickness)
    x0, y0, x1, y1 = t.box
    reach = border + thickness + 2            # anti-aliased stroke edges can pass the box
    x0, y0 = max(x0 - reach, 0), max(y0 - reach, 0)
    x1, y1 = min(x1 + reach, shape[1]), min(y1 + reach, shape[0])
    if x1 <= x0 or y1 <= y0:
        return None
    core = np.zeros((y1 - y0, x1 - x0), np.uint8)
    _put(core, t, (x0, y0))
    # Dilated from where the stroke covers at least half a pixel (its geometric edge), so the
    # ring is fully dark for the whole border beyond the stroke and soft only at its own edge.
    outline = cv2.dilate(cv2.add(core, core), _disc(border))       # the sum saturates at 255
    core.flags.writeable = outline.flags.writeable = False
    return x0, y0, core, outline


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
