"""The corner text read back from the composed screen: the DAP's unit is written cm² with a
raised, smaller 2, and the lines of a corner stand one line pitch apart.

Ground truth: the screen's own sizes worked by hand (one text line is 1/30 of the screen's
height: 34 px on a 1024-line monitor, 36 px on a 1080-line one; strokes of a 17th of that,
rounded: 2 px; a margin of a third of a line) and OpenCV's own measure of the text at the
font scale for a cap height of 0.55 of a line; the positions of the glyphs are read from the
pixels.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from appliance.display.compositor import Compositor, Overlay
from appliance.display.text import FONT

#: (width, height) -> (line pitch, stroke, margin) in pixels, worked by hand from the height.
#: On 780 lines a line is 26 px and its stroke 26 / 17 = 1.53, rounded: 2 px.
SCREENS = {(1280, 1024): (34, 2, 11), (1920, 1080): (36, 2, 12), (1040, 780): (26, 2, 8)}
DARK = np.zeros((64, 64), np.float32)


def lit(frame: np.ndarray, level: int = 200) -> np.ndarray:
    """Where the screen shows text brighter than `level` in every channel (white or grey ink)."""
    return (frame > level).all(axis=2)


def rows_of(mask: np.ndarray) -> np.ndarray:
    return np.nonzero(mask.any(axis=1))[0]


def runs(rows: np.ndarray) -> list[tuple[int, int]]:
    """Consecutive rows grouped: (first, last) of each run."""
    out: list[tuple[int, int]] = []
    for r in rows:
        if out and r == out[-1][1] + 1:
            out[-1] = (out[-1][0], int(r))
        else:
            out.append((int(r), int(r)))
    return out


@pytest.mark.parametrize("size", list(SCREENS))
def test_the_dap_unit_ends_in_a_raised_small_two(size):
    """"DAP  1.23 Gy cm" and then a 2 above the line's middle, smaller than the capitals: cm²."""
    width, height = size
    line, stroke, margin = SCREENS[size]
    comp = Compositor(width, height)
    frame = comp.compose(DARK, Overlay(dap_gy_cm2=1.234), now=0.0)
    scale = cv2.getFontScaleFromHeight(FONT, round(line * 0.55), stroke)
    text = "DAP  1.23 Gy cm"
    (w, _), base = cv2.getTextSize(text, FONT, scale, stroke)
    (w_dap, _), _ = cv2.getTextSize("DAP", FONT, scale, stroke)
    (w_two, _), _ = cv2.getTextSize("2", FONT, scale, stroke)
    baseline = height - margin - base               # the bottom line, nearest the corner
    band = slice(baseline - line + base + stroke + 2, height)   # this line's rows, clear of the line above
    ink = lit(frame)[band]
    caps = rows_of(ink[:, margin:margin + w_dap])  # "DAP": capitals standing on the baseline
    sup = ink[:, margin + w + 1:margin + w + w_two + stroke + 2]
    sup_rows = rows_of(sup)
    assert caps.size and sup.sum() > 10, "no 2 after 'cm': the DAP's unit reads cm, not cm²"
    cap_h = caps.max() - caps.min()
    # Raised: its foot well above the capitals' (the baseline), its head no higher than theirs.
    assert sup_rows.max() <= caps.max() - 0.3 * cap_h
    assert sup_rows.min() >= caps.min() - stroke
    # Small: well under the capitals' height (drawn at 0.6 of the line's font scale).
    assert sup_rows.max() - sup_rows.min() <= 0.75 * cap_h
    # Nothing further along the line: one 2, narrower than a full-size one.
    assert not ink[:, margin + w + w_two + stroke + 2:width // 2].any()


@pytest.mark.parametrize("size", list(SCREENS))
def test_the_top_right_lines_stand_one_line_pitch_apart(size):
    """Mode, technique, zoom and collimation, right-aligned one under another: every line ends
    on its baseline (no descenders in these lines), and the baselines are one line pitch apart,
    the first a margin plus a line's cap height below the top."""
    width, height = size
    line, stroke, margin = SCREENS[size]
    comp = Compositor(width, height)
    overlay = Overlay(mode="continuous", technique=(75.0, 2.0), zoom=1, fov_mm=230.0, collimation_mm=(100.0, 80.0))
    frame = comp.compose(DARK, overlay, now=0.0)
    ink = lit(frame, 150)[:height // 3, width - margin - 60:]       # the lines' last letters (the grey COLL line too)
    lines = runs(rows_of(ink))
    assert len(lines) == 4, lines
    feet = [last for _, last in lines]
    assert np.diff(feet).tolist() == [line] * 3
    scale = cv2.getFontScaleFromHeight(FONT, round(line * 0.55), stroke)
    (_, h), _ = cv2.getTextSize("CONTINUOUS", FONT, scale, stroke)
    assert abs(feet[0] - (margin + h)) <= stroke


@pytest.mark.parametrize("size", list(SCREENS))
def test_the_top_left_lines_stand_one_line_pitch_apart(size):
    """Case, operator and fluoroscope (the cached layer), left-aligned from the margin."""
    width, height = size
    line, stroke, margin = SCREENS[size]
    comp = Compositor(width, height)
    frame = comp.compose(DARK, Overlay(case="CHEST", operator="AB", fluoroscope="ROOM 1"), now=0.0)
    ink = lit(frame, 150)[:height // 3, :margin + 40]               # "CASE", "OPER", "ROOM": capitals
    lines = runs(rows_of(ink))
    assert len(lines) == 3, lines
    assert np.diff([last for _, last in lines]).tolist() == [line] * 2
    assert np.diff([first for first, _ in lines]).tolist() == [line] * 2
    # The first letter of each line begins a margin in (its stroke's anti-aliased edge aside).
    cols = np.nonzero(ink.any(axis=0))[0]
    assert margin - stroke <= cols.min() <= margin + stroke



def test_a_small_screen_keeps_the_least_line_pitch_of_12_px():
    """Under 375 lines a thirtieth of the height is under 12.5 px: the pitch stays 12 px, the
    least at which the corner text (a cap height of 0.55 x 12 = 7 px) stays legible. On a
    320 x 256 screen (256 / 30 = 8.5) the top-left lines end 12 px apart, read from the pixels
    (threshold 100: the grey fluoroscope line's 1 px strokes are dimmer than 150)."""
    comp = Compositor(320, 256)
    frame = comp.compose(DARK, Overlay(case="CHEST", operator="AB", fluoroscope="ROOM 1"), now=0.0)
    lines = runs(rows_of(lit(frame, 100)[:256 // 3, :6 + 40]))      # margin max(6, 12 // 3) = 6
    assert len(lines) == 3, lines
    assert np.diff([last for _, last in lines]).tolist() == [12, 12]
    assert np.diff([first for first, _ in lines]).tolist() == [12, 12]

def texts_of(comp: Compositor, overlay: Overlay) -> dict[str, object]:
    return {t.text: t for t in comp.text_layout(overlay, now=0.0)}


def test_the_corner_lines_read_the_overlay_as_written():
    """What each corner says, typed here from the overlay: the mode in capitals, the technique
    in whole kV and tenths of mA, the labels in capitals, the breathing line as given, and the
    air kerma rate while exposing however small it is."""
    comp = Compositor(1280, 1024)
    lines = texts_of(comp, Overlay(live=True, mode="pulsed 15", technique=(81.4, 2.34), air_kerma_mgy=1.0,
                                   air_kerma_rate_mgy_per_min=0.4, invert=True, breathing="BREATHING 12/min"))
    for text in ("PULSED 15", "81 kV   2.3 mA", "AIR KERMA  1.00 mGy   0.4 mGy/min", "INVERT", "BREATHING 12/min", "LIVE"):
        assert text in lines, (text, sorted(lines))
    held = texts_of(comp, Overlay(live=False, breath_hold=True, breathing="BREATHING 12/min"))
    assert "BREATH HOLD" in held and "BREATHING 12/min" not in held and "HOLD" in held


def test_the_labels_stand_half_a_margin_above_the_live_marker_right_aligned():
    """On 1280 x 1024 (margin 11 px): the lowest label's text ends (its baseline plus OpenCV's
    depth of it) 5 px above the top of the LIVE marker's box; each label ends a margin from the
    right edge; the next label one line (34 px) higher."""
    line, stroke, margin = SCREENS[(1280, 1024)]
    comp = Compositor(1280, 1024)
    lines = texts_of(comp, Overlay(live=True, invert=True, breath_hold=True))
    live, invert, hold = lines["LIVE"], lines["INVERT"], lines["BREATH HOLD"]
    scale = cv2.getFontScaleFromHeight(FONT, round(line * 0.55), stroke)
    (w_inv, _), base_inv = cv2.getTextSize("INVERT", FONT, scale, stroke)
    (w_hold, _), base_hold = cv2.getTextSize("BREATH HOLD", FONT, scale, stroke)
    assert invert.org[1] + base_inv == live.box[1] - margin // 2
    assert invert.org[0] + w_inv == 1280 - margin and hold.org[0] + w_hold == 1280 - margin
    assert (invert.org[1] + base_inv) - (hold.org[1] + base_hold) == line


@pytest.mark.parametrize("live, fill", [(True, (255, 214, 0)), (False, (60, 60, 60))])
def test_the_markers_box_is_padded_by_its_stroke_and_a_pixel(live, fill):
    """On 640 x 512 (line 17 px, stroke 1, the marker's 2, margin 6, inset 3): the marker ends
    9 px in from the right and stands on the dose line's baseline, a margin above that line's
    depth; its box padded by its stroke plus one (3 px) round OpenCV's measure of it, and widened
    half a margin (3 px) each side: the filled pixels span exactly that, read from the screen."""
    comp = Compositor(640, 512)
    text = "LIVE" if live else "HOLD"
    font = cv2.FONT_HERSHEY_DUPLEX
    scale = cv2.getFontScaleFromHeight(font, 14, 2)
    (w, h), base = cv2.getTextSize(text, font, scale, 2)
    _, dose_depth = cv2.getTextSize("DAP  0.000 Gy cm", FONT, cv2.getFontScaleFromHeight(FONT, 9, 1), 1)
    org = (640 - 9 - w, 512 - 6 - dose_depth)
    frame = comp.compose(DARK, Overlay(live=live), now=0.0)
    filled = np.all(frame == fill, axis=2)
    filled[:, :320] = False                                  # the bottom-right corner only
    filled[:256] = False
    rows, cols = np.nonzero(filled)
    assert (cols.min(), cols.max()) == (org[0] - 3 - 3, org[0] + w + 3 + 3)
    assert (rows.min(), rows.max()) == (org[1] - h - 3, org[1] + base + 3)


@pytest.mark.parametrize("size", [*SCREENS, (640, 512)])
@pytest.mark.parametrize("live", [True, False])
def test_the_bottom_corners_stand_on_one_baseline(size, live):
    """Read from the screen: the lowest row of the capitals "DAP" (bottom left, white) and of the
    marker's letters (bottom right: white HOLD on grey, or black LIVE on yellow) is the same
    row, to a pixel (the marker's stroke is one pixel wider, half of it below the baseline)."""
    width, height = size
    comp = Compositor(width, height)
    frame = comp.compose(DARK, Overlay(live=live), now=0.0)
    dap = next(t for t in comp.text_layout(Overlay(live=live), now=0.0) if t.text.startswith("DAP"))
    x0, y0, x1, y1 = dap.box
    (w_dap, _), _ = cv2.getTextSize("DAP", FONT, dap.scale, dap.thickness)
    left = lit(frame)[y0:y1, x0:dap.org[0] + w_dap]
    marker = next(t for t in comp.text_layout(Overlay(live=live), now=0.0) if t.text in ("LIVE", "HOLD"))
    mx0, my0, mx1, my1 = marker.box
    box = frame[my0:my1, mx0:mx1].astype(int)
    if live:
        letters = (box < 100).all(axis=2)          # black ink on the yellow box
    else:
        letters = (box > 200).all(axis=2)          # white ink on the grey box
    feet_left = y0 + rows_of(left).max()
    feet_right = my0 + rows_of(letters).max()
    assert abs(feet_left - feet_right) <= 1, (feet_left, feet_right)
