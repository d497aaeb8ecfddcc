"""What the monitor of the fluoroscope shows: the X-ray image in its field of view, and the overlays.

The image from the renderer is fitted to the screen height and centred (letterboxed; a
non-square detector keeps its aspect ratio); an image intensifier's field of view is the
circle inscribed in that square. Text sits in
the corners outside the circle, as on a clinical monitor: case, operator and fluoroscope top
left; mode, zoom, field of view and collimation top right; fluoroscopy time, reference air
kerma and dose-area product bottom left; the LIVE / HOLD marker bottom right. Warnings are
amber banners across the top, the five-minute alarm a flashing red banner at the bottom.

Electronic collimation is drawn on whatever image is shown, live or held: the parts of the
field outside the blade opening are darkened and the blade edges drawn, as units with
virtual collimation show where the blades will be before the next exposure.

Sizes scale with the screen height (one text line is 1/30 of it), so 1920x1080 and
1280x1024 monitors both read well from the operator's position. Everything that depends
only on the screen size (the circle mask, fonts, positions) is computed once; the text that
changes only with the session (case, operator, fluoroscope) is drawn into a cached layer.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import cv2
import numpy as np

from .text import (
    AMBER,
    BLACK,
    FONT,
    FONT_BOLD,
    GREEN,
    GREY,
    RED,
    WHITE,
    YELLOW,
    TextLine,
    dose_number,
    draw_text,
    fluoro_time_clock,
    fluoro_time_minutes,
    text_size,
    wrap_text,
)

#: Brightness kept outside the collimator opening (fraction of the image value).
COLLIMATED_BRIGHTNESS = 0.3
#: The alarm banner is on for the first half of each period (s).
ALARM_FLASH_PERIOD_S = 1.0
#: At most this many warning banners are shown; the last one says how many more there are.
MAX_WARNINGS = 4
#: Grey level (of 255) of the drawn blade edges: visible on black and on bright anatomy.
BLADE_EDGE_GREY = 150
#: Warnings shorter than this (characters) are shown in capitals, as a unit's short alerts are.
SHORT_WARNING_CHARS = 40
#: The smallest screen the layout works on (pixels a side).
MIN_SCREEN_PX = 64


@dataclass
class Overlay:
    """Everything besides the image that the monitor shows; plain data filled in by the daemon.

    Units: `fov_mm` and `collimation_mm` (horizontal, vertical blade openings) at the
    detector plane in mm, `fluoro_time_s` in s, `air_kerma_mgy` in mGy and its rate while
    exposing in mGy/min (0 otherwise), `dap_gy_cm2` in Gy cm^2, `fps` in frames per second. `zoom` is the zoom level, 1 (widest) to 4.
    `collimation_mm` None means fully open.
    """

    live: bool = False
    zoom: int = 1
    fov_mm: float = 300.0
    collimation_mm: tuple[float, float] | None = None
    fluoro_time_s: float = 0.0
    air_kerma_mgy: float = 0.0
    air_kerma_rate_mgy_per_min: float = 0.0
    dap_gy_cm2: float = 0.0
    mode: str = ""
    technique: tuple[float, float] | None = None   # (kV, mA) the exposure control set, shown while exposing
    alarm: bool = False
    alarm_since: float | None = None   # when the alarm began sounding (the compose clock's s); its flash starts lit there
    saved_flash: bool = False
    invert: bool = False               # shows the INVERT label; the image arrives already inverted
    breath_hold: bool = False
    breathing: str = ""             # controllable breathing: rate and depth (empty: the case has none)
    case: str = ""
    operator: str = ""
    fluoroscope: str = ""
    warnings: list[str] = field(default_factory=list)
    fps: float | None = None
    # Teaching (appliance/teaching/live.py): the shot counter (None: not shown), the current
    # task line, and the cue after a save ("task met: ..." or why not).
    shots: int | None = None
    task: str = ""
    cue: str = ""


class Compositor:
    """Builds the screen from the rendered image and the overlay; one instance per screen size."""

    def __init__(self, width: int, height: int, circular_fov: bool = True):
        if width < MIN_SCREEN_PX or height < MIN_SCREEN_PX:
            raise ValueError(f"screen must be at least {MIN_SCREEN_PX}x{MIN_SCREEN_PX} pixels, got {width}x{height}")
        self.width, self.height, self.circular_fov = width, height, circular_fov
        self.side = min(width, height)                        # the image square (pixels)
        self.x0 = (width - self.side) // 2
        self.y0 = (height - self.side) // 2
        self.radius = self.side / 2.0                          # the field of view's circle (pixels)
        self.centre = (self.x0 + self.side / 2.0, self.y0 + self.side / 2.0)
        self.line = max(12, round(height / 30))                # text line pitch (pixels)
        self.thickness = max(1, round(self.line / 17))
        self.scale = cv2.getFontScaleFromHeight(FONT, round(self.line * 0.55), self.thickness)
        self.big_scale = cv2.getFontScaleFromHeight(FONT_BOLD, round(self.line * 0.85), self.thickness + 1)
        self.margin = max(6, self.line // 3)
        yy, xx = np.mgrid[0:self.side, 0:self.side]
        c = (self.side - 1) / 2.0
        inside = (xx - c) ** 2 + (yy - c) ** 2 <= self.radius ** 2 if circular_fov else np.ones_like(xx, bool)
        self._mask = np.where(inside, 255, 0).astype(np.uint8)
        self._dim_lut = (np.arange(256) * COLLIMATED_BRIGHTNESS).astype(np.uint8)
        self._static_key: tuple | None = None
        self._static_layer = np.zeros((height, width, 3), np.uint8)
        self._static_mask = np.zeros((height, width), np.uint8)
        self._static_boxes: list[tuple[int, int, int, int]] = []
        self._starting = self._starting_square()

    # ------------------------------------------------------------------ layout

    def _corner_lines(self, texts: list[tuple], corner: str, scale: float | None = None, font: int = FONT,
                      thickness: int | None = None, inset: int = 0, baseline: int | None = None) -> list[TextLine]:
        """Lay out lines, (text, colour[, superscript]), in a screen corner ('tl', 'tr', 'bl', 'br'),
        the first line nearest the corner, `inset` pixels further in than the margin; in a bottom
        corner the first line on `baseline` (screen row) if given, else a margin above its depth."""
        scale = scale or self.scale
        thickness = thickness or self.thickness
        laid = []
        edge = self.margin + inset
        for i, (text, color, *superscript) in enumerate(texts):
            sup = superscript[0] if superscript else ""
            w, h, base = text_size(text, font, scale, thickness, sup)
            pitch = max(self.line, round(h * 1.5))
            x = edge if corner[1] == "l" else self.width - edge - w
            if corner[0] == "t":
                y = edge + h + i * pitch
            else:
                y = (self.height - edge - base if baseline is None else baseline) - i * pitch
            laid.append(TextLine(text, (x, y), scale, color, font, thickness, sup))
        return laid

    def _static_texts(self, overlay: Overlay) -> list[TextLine]:
        lines = [(f"CASE  {overlay.case}", WHITE), (f"OPERATOR  {overlay.operator}", WHITE),
                 (overlay.fluoroscope, GREY)]
        return self._corner_lines([(s, c) for s, c in lines if s.strip()], "tl")

    def _refresh_static(self, overlay: Overlay) -> None:
        key = (overlay.case, overlay.operator, overlay.fluoroscope)
        if key == self._static_key:
            return
        self._static_layer[...] = 0
        self._static_mask[...] = 0
        self._static_boxes = []
        for t in self._static_texts(overlay):
            draw_text(self._static_layer, t)
            draw_text(self._static_mask, TextLine(t.text, t.org, t.scale, 255, t.font, t.thickness, t.sup), outline_color=255)
            x0, y0, x1, y1 = t.box
            self._static_boxes.append((max(x0, 0), max(y0, 0), min(x1, self.width), min(y1, self.height)))
        self._static_key = key

    def text_layout(self, overlay: Overlay, now: float | None = None) -> list[TextLine]:
        """Every line of text compose() would draw, with its position (for checks of legibility and overlap)."""
        return self._static_texts(overlay) + self._dynamic_texts(overlay, now)

    def _dynamic_texts(self, overlay: Overlay, now: float | None) -> list[TextLine]:
        texts: list[TextLine] = []
        right = []
        if overlay.mode:
            right.append((overlay.mode.upper(), WHITE))
        if overlay.technique is not None:
            right.append((f"{overlay.technique[0]:.0f} kV   {overlay.technique[1]:.1f} mA", WHITE))
        right.append((f"ZOOM {overlay.zoom}   FOV {overlay.fov_mm:.0f} mm", WHITE))
        if overlay.collimation_mm is not None:
            h_mm, v_mm = overlay.collimation_mm
            right.append((f"COLL {h_mm:.0f} x {v_mm:.0f} mm", GREY))
        texts += self._corner_lines(right, "tr")
        left = [(f"DAP  {dose_number(overlay.dap_gy_cm2)} Gy cm", WHITE, "2"),
                (f"AIR KERMA  {dose_number(overlay.air_kerma_mgy)} mGy"
                 # The rate while exposing, as IEC 60601-2-43 asks; it follows the ABC.
                 + (f"   {overlay.air_kerma_rate_mgy_per_min:.1f} mGy/min" if overlay.air_kerma_rate_mgy_per_min > 0 else ""),
                 WHITE),
                (f"FLUORO  {fluoro_time_clock(overlay.fluoro_time_s)}   {fluoro_time_minutes(overlay.fluoro_time_s)}",
                 YELLOW if overlay.alarm else WHITE)]
        if overlay.shots is not None:
            left.append((f"SHOTS  {overlay.shots}", WHITE))
        if overlay.task:
            left.append((overlay.task.upper(), GREEN))
        dose_lines = self._corner_lines(left, "bl")
        texts += dose_lines
        # The marker stands on the dose lines' baseline: its own depth (OpenCV measures it by
        # the glyphs present, and the dose line's "Gy" descends) and inset would set it higher.
        marker = [("LIVE" if overlay.live else "HOLD", BLACK if overlay.live else WHITE)]
        texts += self._corner_lines(marker, "br", scale=self.big_scale, font=FONT_BOLD, thickness=self.thickness + 1,
                                    inset=self.margin // 2, baseline=dose_lines[0].org[1])
        extra = []
        if overlay.invert:
            extra.append(("INVERT", WHITE))
        if overlay.breath_hold:
            extra.append(("BREATH HOLD", AMBER))
        elif overlay.breathing:
            extra.append((overlay.breathing, WHITE))
        if overlay.fps is not None:
            extra.append((f"{overlay.fps:.0f} fps", GREY))
        if extra:
            above = self.height - texts[-1].box[1] + self.margin // 2
            for t in self._corner_lines(extra, "br"):
                texts.append(TextLine(t.text, (t.org[0], t.org[1] - above + self.margin), t.scale, t.color, t.font, t.thickness))
        return texts

    # ------------------------------------------------------------------ pieces of the frame

    def _starting_square(self) -> np.ndarray:
        square = np.full((self.side, self.side), 24, np.uint8)
        cv2.bitwise_and(square, self._mask, dst=square)
        return square

    def _image_square(self, image: np.ndarray, overlay: Overlay) -> np.ndarray:
        if image.ndim != 2:
            raise ValueError(f"image must be (rows, cols), got shape {image.shape}")
        img = np.asarray(image, dtype=np.float32)
        img = np.maximum(img, np.float32(0.0))   # convertScaleAbs would fold negatives up
        img8 = cv2.convertScaleAbs(img, alpha=255.0)           # rounds and saturates at 255
        # No inverting here: the renderer's display LUT owns polarity (overlay.invert is the label).
        rows, cols = img8.shape
        # The longer side fills the square; a non-square detector keeps its aspect ratio.
        w, h = self._fitted(rows, cols)
        interpolation = cv2.INTER_AREA if max(rows, cols) > self.side else cv2.INTER_LINEAR
        if (w, h) == (self.side, self.side):
            square = cv2.resize(img8, (w, h), interpolation=interpolation)
        else:
            square = np.zeros((self.side, self.side), np.uint8)
            x, y = (self.side - w) // 2, (self.side - h) // 2
            square[y:y + h, x:x + w] = cv2.resize(img8, (w, h), interpolation=interpolation)
        self._collimate(square, overlay, w)
        cv2.bitwise_and(square, self._mask, dst=square)
        return square

    def _fitted(self, rows: int, cols: int) -> tuple[int, int]:
        """Displayed (width, height) in screen pixels of a rows x cols image."""
        longest = max(rows, cols)
        return max(1, round(self.side * cols / longest)), max(1, round(self.side * rows / longest))

    def blade_edges(self, overlay: Overlay, image_width_px: int | None = None) -> tuple[int, int, int, int] | None:
        """Opening of the collimator in image-square pixels: (left, top, right, bottom), exclusive ends.

        The image spans `fov_mm` across its displayed width (`image_width_px`, default the
        whole square), so an opening of o mm covers o / fov_mm of that width, centred on the
        central ray; both blade pairs use the same pixels per mm.
        """
        if overlay.collimation_mm is None or overlay.fov_mm <= 0:
            return None
        px_per_mm = (image_width_px or self.side) / overlay.fov_mm
        h_mm, v_mm = overlay.collimation_mm
        half_w = min(max(h_mm, 0.0) * px_per_mm, self.side) / 2.0
        half_h = min(max(v_mm, 0.0) * px_per_mm, self.side) / 2.0
        c = self.side / 2.0
        return (round(c - half_w), round(c - half_h), round(c + half_w), round(c + half_h))

    def _collimate(self, square: np.ndarray, overlay: Overlay, image_width_px: int) -> None:
        edges = self.blade_edges(overlay, image_width_px)
        if edges is None:
            return
        left, top, right, bottom = edges
        for region in (square[:top], square[bottom:], square[top:bottom, :left], square[top:bottom, right:]):
            if region.size:
                cv2.LUT(region, self._dim_lut, dst=region)
        edge = BLADE_EDGE_GREY
        if left > 0:
            square[top:bottom, max(left - 1, 0):left + 1] = edge
            square[top:bottom, right - 1:min(right + 1, self.side)] = edge
        if top > 0:
            square[max(top - 1, 0):top + 1, left:right] = edge
            square[bottom - 1:min(bottom + 1, self.side), left:right] = edge

    def _banner(self, frame: np.ndarray, text: str, y_top: int, fill: tuple[int, int, int], color: tuple[int, int, int],
                from_bottom: bool = False) -> int:
        """A centred filled box holding `text`, wrapped to the image width; returns the y below it
        (or, `from_bottom`, draws it with its bottom at `y_top` and returns the y above it)."""
        lines = wrap_text(text, round(self.side * 0.9) - 2 * self.margin, self.scale, self.thickness)
        (_, h), base = cv2.getTextSize("Xg", FONT, self.scale, self.thickness)
        pitch = h + base + self.margin // 2
        box_w = max(cv2.getTextSize(line, FONT, self.scale, self.thickness)[0][0] for line in lines) + 2 * self.margin
        box_h = pitch * len(lines) + self.margin // 2
        if from_bottom:
            y_top -= box_h
        x = (self.width - box_w) // 2
        cv2.rectangle(frame, (x, y_top), (x + box_w, y_top + box_h), fill, thickness=-1)
        for i, line in enumerate(lines):
            cv2.putText(frame, line, (x + self.margin, y_top + self.margin // 2 + h + i * pitch), FONT, self.scale,
                        color, self.thickness, cv2.LINE_AA)
        return y_top - self.margin // 3 if from_bottom else y_top + box_h + self.margin // 3

    # ------------------------------------------------------------------ the frame

    def _blank(self, out: np.ndarray | None) -> np.ndarray:
        """A black screen to compose on: new, or `out` with all but the image square cleared
        (compose overwrites every pixel of the square)."""
        if out is None:
            return np.zeros((self.height, self.width, 3), np.uint8)
        if out.shape != (self.height, self.width, 3) or out.dtype != np.uint8:
            raise ValueError(f"out must be ({self.height}, {self.width}, 3) uint8, got {out.shape} {out.dtype}")
        y1, x1 = self.y0 + self.side, self.x0 + self.side
        for border in (out[:self.y0], out[y1:], out[self.y0:y1, :self.x0], out[self.y0:y1, x1:]):
            border.fill(0)
        return out

    def compose(self, image: np.ndarray | None, overlay: Overlay, now: float | None = None,
                out: np.ndarray | None = None) -> np.ndarray:
        """The screen as a new (height, width, 3) uint8 RGB array, or drawn into `out` (that
        shape) and returned: a caller showing a frame at video rate keeps one, since a fresh
        4-5 MB array costs its page faults on every frame.

        `image`: (rows, cols) float32 display values in [0, 1] from the renderer (1 bright),
        or None before the first frame (a "starting" screen). `now` (s, monotonic clock)
        sets the phase of the flashing alarm; default time.monotonic().
        """
        now = time.monotonic() if now is None else now
        frame = self._blank(out)
        square = self._starting if image is None else self._image_square(image, overlay)
        cv2.cvtColor(square, cv2.COLOR_GRAY2RGB, dst=frame[self.y0:self.y0 + self.side, self.x0:self.x0 + self.side])
        if overlay.saved_flash:
            cx, cy = round(self.centre[0] - 0.5), round(self.centre[1] - 0.5)
            cv2.circle(frame, (cx, cy), round(self.radius) - self.thickness * 2, WHITE, self.thickness * 3, cv2.LINE_AA)
        self._refresh_static(overlay)
        for x0, y0, x1, y1 in self._static_boxes:
            cv2.copyTo(self._static_layer[y0:y1, x0:x1], self._static_mask[y0:y1, x0:x1], frame[y0:y1, x0:x1])
        for t in self._dynamic_texts(overlay, now):
            if t.text in ("LIVE", "HOLD"):
                x0, y0, x1, y1 = t.box
                cv2.rectangle(frame, (x0 - self.margin // 2, y0), (x1 + self.margin // 2, y1),
                              YELLOW if overlay.live else (60, 60, 60), thickness=-1)
                cv2.putText(frame, t.text, t.org, t.font, t.scale, t.color, t.thickness, cv2.LINE_AA)
            else:
                draw_text(frame, t)
        y = self.margin + 3 * self.line     # below the corner text, which is never covered
        if image is None:
            label = "STARTING"
            (w, h), _ = cv2.getTextSize(label, FONT_BOLD, self.big_scale, self.thickness + 1)
            cv2.putText(frame, label, (round(self.centre[0] - w / 2), round(self.centre[1] + h / 2)), FONT_BOLD,
                        self.big_scale, GREY, self.thickness + 1, cv2.LINE_AA)
        warnings = list(overlay.warnings)
        if len(warnings) > MAX_WARNINGS:
            warnings = warnings[:MAX_WARNINGS - 1] + [f"... and {len(warnings) - MAX_WARNINGS + 1} more warnings"]
        for warning in warnings:
            text = warning.upper() if len(warning) < SHORT_WARNING_CHARS else warning
            y = self._banner(frame, text, y, AMBER, BLACK)
        if overlay.saved_flash:
            y = self._banner(frame, "IMAGE SAVED", max(y, round(self.height * 0.2)), GREEN, BLACK)
        if overlay.cue:
            met = overlay.cue.startswith("task met")
            self._banner(frame, overlay.cue.upper(), max(y, round(self.height * 0.2)), GREEN if met else AMBER, BLACK)
        # The flash runs from the alarm's onset, so its banner is lit the moment it sounds.
        since = 0.0 if overlay.alarm_since is None else overlay.alarm_since
        if overlay.alarm and ((now - since) % ALARM_FLASH_PERIOD_S) < ALARM_FLASH_PERIOD_S / 2:
            self._banner(frame, f"FLUOROSCOPY TIME ALARM  {fluoro_time_clock(overlay.fluoro_time_s)}  -  PRESS ALARM RESET",
                         self.height - self.margin - 3 * self.line, RED, WHITE, from_bottom=True)
        return frame
