"""The blades, their dimming and the banners, pixel for pixel.

Ground truth: the blade opening worked by hand (a 512 px square showing 300 mm, so 150 x 75 mm
opens columns 128..383 and rows 192..319), dimming to 3/10 of each grey level in integers,
two-pixel blade lines of grey 150 along each edge; a banner is a filled box as wide as its
widest line plus a margin each side, one line pitch (OpenCV's own text height and depth of
"Xg" plus half a margin) a line, and the next banner starts a third of a margin below it.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from appliance.display.compositor import Compositor, Overlay
from appliance.display.text import AMBER, BLACK, FONT, GREEN, RED, WHITE, wrap_text

SIDE = 512
EDGE_GREY = 150


def grey_ramp() -> tuple[np.ndarray, np.ndarray]:
    """A SIDE x SIDE image holding every grey level in every region, and its 8-bit values."""
    levels = (np.arange(SIDE * SIDE).reshape(SIDE, SIDE) * 7) % 256
    return (levels / 255.0).astype(np.float32), levels


def expected_square(levels: np.ndarray, opening: tuple[int, int, int, int]) -> np.ndarray:
    left, top, right, bottom = opening
    rows, cols = np.mgrid[0:SIDE, 0:SIDE]
    inside = (cols >= left) & (cols < right) & (rows >= top) & (rows < bottom)
    out = np.where(inside, levels, (3 * levels) // 10)
    band = (rows >= top) & (rows < bottom)
    span = (cols >= left) & (cols < right)
    if left > 0:
        out[band & ((cols == left - 1) | (cols == left) | (cols == right - 1) | (cols == right))] = EDGE_GREY
    if top > 0:
        out[span & ((rows == top - 1) | (rows == top) | (rows == bottom - 1) | (rows == bottom))] = EDGE_GREY
    return out.astype(np.uint8)


@pytest.mark.parametrize("collimation_mm, opening", [
    ((150.0, 75.0), (128, 192, 384, 320)),        # both pairs in
    ((900.0, 75.0), (0, 192, 512, 320)),          # the horizontal pair wide open: no vertical lines
    ((150.0, 900.0), (128, 0, 384, 512)),         # the vertical pair wide open: no horizontal lines
    ((298.8, 298.8), (1, 1, 511, 511)),           # a pixel in from every side: the lines reach the square's edge
    ((0.0, 0.0), (256, 256, 256, 256)),           # shut: all dimmed, the lines meet in the middle
    (None, (0, 0, 512, 512)),                     # no collimation
])
def test_blades_dim_outside_the_opening_and_draw_two_pixel_edges(collimation_mm, opening):
    comp = Compositor(640, SIDE, circular_fov=False)
    image, levels = grey_ramp()
    square = comp._image_square(image, Overlay(fov_mm=300.0, collimation_mm=collimation_mm))
    expected = expected_square(levels, opening)
    wrong = np.argwhere(square != expected)
    assert wrong.size == 0, (len(wrong), wrong[:5].tolist(), [(int(square[tuple(p)]), int(expected[tuple(p)]))
                                                             for p in wrong[:5]])


def test_the_circle_masks_the_collimated_square():
    comp = Compositor(640, SIDE)
    image, levels = grey_ramp()
    square = comp._image_square(image, Overlay(fov_mm=300.0, collimation_mm=(150.0, 75.0)))
    rows, cols = np.mgrid[0:SIDE, 0:SIDE]
    c = (SIDE - 1) / 2
    inside = (cols - c) ** 2 + (rows - c) ** 2 <= (SIDE / 2) ** 2
    assert np.array_equal(square, np.where(inside, expected_square(levels, (128, 192, 384, 320)), 0))


def banner_box(comp: Compositor, text: str) -> tuple[list[str], int, int, int, int]:
    """Lines, width, height, text height above the baseline and the line pitch, by the rule above."""
    lines = wrap_text(text, round(comp.side * 0.9) - 2 * comp.margin, comp.scale, comp.thickness)
    (_, h), base = cv2.getTextSize("Xg", FONT, comp.scale, comp.thickness)
    pitch = h + base + comp.margin // 2
    width = max(cv2.getTextSize(line, FONT, comp.scale, comp.thickness)[0][0] for line in lines) + 2 * comp.margin
    return lines, width, pitch * len(lines) + comp.margin // 2, h, pitch


def drawn_banner(comp: Compositor, text: str, top: int, fill, color) -> np.ndarray:
    """The banner drawn from the rule with OpenCV's primitives: the box, then each line at its pitch."""
    frame = np.zeros((comp.height, comp.width, 3), np.uint8)
    lines, w, h_box, h, pitch = banner_box(comp, text)
    x = (comp.width - w) // 2
    frame[top:top + h_box + 1, x:x + w + 1] = fill
    for i, line in enumerate(lines):
        cv2.putText(frame, line, (x + comp.margin, top + comp.margin // 2 + h + i * pitch), FONT, comp.scale, color,
                    comp.thickness, cv2.LINE_AA)
    return frame


# 1280 x 1024 has a margin of 11 px, not a multiple of 3: the gap below a banner is 3 px, not 3.67.
@pytest.mark.parametrize("size", [(640, 512), (1280, 1024), (1920, 1080)])
def test_a_banner_is_its_box_and_its_lines_exactly(size):
    comp = Compositor(*size)
    text = ("camera lost: the webcam at usb-0000:00:14.0-2 stopped sending frames; check its cable and that "
            "no other program holds the device")
    lines, w, h_box, _, _ = banner_box(comp, text)
    assert len(lines) >= 2
    frame = np.zeros((comp.height, comp.width, 3), np.uint8)
    below = comp._banner(frame, text, 100, AMBER, BLACK)
    assert np.array_equal(frame, drawn_banner(comp, text, 100, AMBER, BLACK))
    assert below == 100 + h_box + comp.margin // 3
    # From the bottom: the box ends at the given row, and the next one goes a third of a margin above.
    frame[...] = 0
    above = comp._banner(frame, "PRESS ALARM RESET", 400, RED, WHITE, from_bottom=True)
    _, _, h_box, _, _ = banner_box(comp, "PRESS ALARM RESET")
    assert np.array_equal(frame, drawn_banner(comp, "PRESS ALARM RESET", 400 - h_box, RED, WHITE))
    assert above == 400 - h_box - comp.margin // 3 and isinstance(above, int)


def boxes(frame: np.ndarray, fill) -> list[tuple[int, int, int, int]]:
    """(top, bottom, left, right) of each run of rows holding the fill colour, inclusive."""
    mask = np.all(frame == fill, axis=2)
    rows = mask.any(axis=1)
    out, r = [], 0
    while r < len(rows):
        if rows[r]:
            end = r
            while end + 1 < len(rows) and rows[end + 1]:
                end += 1
            cols = np.flatnonzero(mask[r:end + 1].any(axis=0))
            out.append((r, end, int(cols[0]), int(cols[-1])))
            r = end + 1
        else:
            r += 1
    return out


def expected_boxes(comp: Compositor, texts: list[str], top: int) -> list[tuple[int, int, int, int]]:
    out = []
    for text in texts:
        _, w, h_box, _, _ = banner_box(comp, text)
        x = (comp.width - w) // 2
        out.append((top, top + h_box, x, x + w))
        top += h_box + comp.margin // 3
    return out


def test_warnings_stack_from_below_the_corner_text_short_ones_in_capitals_the_fourth_counts_the_rest():
    comp = Compositor(640, SIDE)
    dark = np.zeros((64, 64), np.float32)
    first = comp.margin + 3 * comp.line                     # below the three lines of corner text
    long = "the pedal at /dev/serial/by-id/usb-FTDI was unplugged; plug it back in"   # 40 characters or more: as written
    frame = comp.compose(dark, Overlay(warnings=["camera lost", long]), now=0.75)
    assert boxes(frame, AMBER) == expected_boxes(comp, ["CAMERA LOST", long], first)
    seven = [f"warning {k}" for k in range(7)]
    frame = comp.compose(dark, Overlay(warnings=seven), now=0.75)
    shown = ["WARNING 0", "WARNING 1", "WARNING 2", "... AND 4 MORE WARNINGS"]
    assert boxes(frame, AMBER) == expected_boxes(comp, shown, first)
    # Exactly four are all shown; the text of each is the one drawn by the rule.
    four = seven[:4]
    frame = comp.compose(dark, Overlay(warnings=four), now=0.75)
    assert boxes(frame, AMBER) == expected_boxes(comp, [w.upper() for w in four], first)
    drawn = drawn_banner(comp, "WARNING 3", expected_boxes(comp, [w.upper() for w in four], first)[3][0], AMBER, BLACK)
    t, b, l, r = boxes(drawn, AMBER)[0]
    assert np.array_equal(frame[t:b + 1, l:r + 1], drawn[t:b + 1, l:r + 1])
    # 39 characters is short, 40 is not.
    assert len("x" * 39) < 40
    frame = comp.compose(dark, Overlay(warnings=["x" * 39, "y" * 40]), now=0.75)
    assert boxes(frame, AMBER) == expected_boxes(comp, ["X" * 39, "y" * 40], first)


def test_saved_and_cue_banners_go_below_the_warnings_and_never_above_a_fifth_of_the_screen():
    comp = Compositor(640, SIDE)
    dark = np.zeros((64, 64), np.float32)
    fifth = round(SIDE * 0.2)
    # No warnings: the saved banner at a fifth of the height, the cue right below it.
    frame = comp.compose(dark, Overlay(saved_flash=True, cue="task met: lateral view"), now=0.75)
    assert boxes(frame, GREEN) == expected_boxes(comp, ["IMAGE SAVED", "TASK MET: LATERAL VIEW"], fifth)
    # A cue that is not met is amber; without a saved banner it takes the saved banner's place.
    frame = comp.compose(dark, Overlay(cue="not yet: the spine is not centred"), now=0.75)
    assert boxes(frame, AMBER) == expected_boxes(comp, ["NOT YET: THE SPINE IS NOT CENTRED"], fifth)
    # Four warnings reach below a fifth: the saved banner follows them.
    warnings = [f"warning {k}" for k in range(4)]
    stacked = expected_boxes(comp, [w.upper() for w in warnings] + ["IMAGE SAVED"], comp.margin + 3 * comp.line)
    assert stacked[3][1] > fifth
    frame = comp.compose(dark, Overlay(warnings=warnings, saved_flash=True), now=0.75)
    assert boxes(frame, GREEN) == stacked[4:]


def test_the_alarm_banner_sits_on_the_bottom_text_lines_and_reads_the_clock():
    comp = Compositor(640, SIDE)
    overlay = Overlay(alarm=True, fluoro_time_s=301.0, alarm_since=0.0)
    frame = comp.compose(np.zeros((64, 64), np.float32), overlay, now=0.25)
    text = "FLUOROSCOPY TIME ALARM  05:01  -  PRESS ALARM RESET"
    bottom = SIDE - comp.margin - 3 * comp.line
    _, w, h_box, _, _ = banner_box(comp, text)
    x = (comp.width - w) // 2
    assert boxes(frame, RED) == [(bottom - h_box, bottom, x, x + w)]
    drawn = drawn_banner(comp, text, bottom - h_box, RED, WHITE)
    assert np.array_equal(frame[bottom - h_box:bottom + 1, x:x + w + 1], drawn[bottom - h_box:bottom + 1, x:x + w + 1])


def text_coverage(shape: tuple[int, int], lines) -> np.ndarray:
    """Coverage (0-255) of the lines' own strokes, superscripts included, with OpenCV's text primitive."""
    core = np.zeros(shape, np.uint8)
    for t in lines:
        cv2.putText(core, t.text, t.org, t.font, t.scale, 255, t.thickness, cv2.LINE_AA)
        if t.sup:   # raised by 0.4 of the text's height, at 0.6 of its scale, after the text
            (w, h), _ = cv2.getTextSize(t.text, t.font, t.scale, t.thickness)
            cv2.putText(core, t.sup, (t.org[0] + w, t.org[1] - round(h * 0.4)), t.font, 0.6 * t.scale, 255,
                        t.thickness, cv2.LINE_AA)
    return core


def distance_to(mask: np.ndarray) -> np.ndarray:
    """Exact Euclidean distance (px) of every pixel to the nearest pixel of `mask`."""
    return cv2.distanceTransform(np.where(mask, 0, 255).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)


@pytest.mark.parametrize("thickness, border", [(1, 1), (2, 2), (3, 2), (4, 3)])
def test_text_is_drawn_over_a_dark_outline_a_border_wider_each_side(thickness, border):
    """A black ring max(1, thickness // 2 + 1) px wide (1, 2, 2 and 3 px for strokes of 1 to
    4 px, worked by hand) all round the letters: every pixel within the border of the stroke (the
    pixels the text covers at least half) is black with the text's colour laid over it in
    proportion to its coverage; farther than the border from any text pixel nothing changes."""
    from appliance.display.text import FONT_BOLD, TextLine, draw_text
    # 200, not 128: a blend that scaled by 1/256 keeps 128 (127.5 rounds to it) but makes 200 199.
    canvas = np.full((80, 400, 3), 200, np.uint8)
    for font in (FONT, FONT_BOLD):
        t = TextLine("DAP 1.23 Gy cm", (10, 50), 1.0, (255, 214, 0), font, thickness, "2")
        got = canvas.copy()
        draw_text(got, t)
        core = text_coverage(canvas.shape[:2], [t])
        stroke = core >= 128
        near = distance_to(stroke) <= border
        on_black = np.rint(np.array(t.color, np.float64) * core[..., None] / 255.0)
        assert np.array_equal(got[near], on_black[near]), (font, thickness)
        # The ring outside the stroke is about the border times the stroke's edge long.
        edge = stroke & ~cv2.erode(stroke.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
        assert (near & ~stroke).sum() > 0.6 * border * edge.sum(), (font, thickness)
        assert (got[distance_to(core > 0) > border + 1e-3] == 200).all(), (font, thickness)


def static_text_masks(comp: Compositor, overlay: Overlay) -> tuple[np.ndarray, np.ndarray]:
    """Coverage (0-255) of the corner text's own strokes, and its outline by the rule: 255 within
    the border of the stroke (where the text covers at least half), 0 farther than the border
    from any text pixel (partly covered between)."""
    lines = comp._static_texts(overlay)                  # the title and the operator's label
    core = text_coverage((comp.height, comp.width), lines)
    border = max(1, lines[0].thickness // 2 + 1)
    outline = np.full_like(core, 128)
    outline[distance_to(core >= 128) <= border] = 255
    outline[distance_to(core > 0) > border + 1e-3] = 0
    return core, outline


TITLE = Overlay(case="Child torso VCUG, a long case title that runs into the image")


def test_the_cached_corner_text_is_white_on_its_black_outline_over_the_image_and_nothing_else_changes():
    comp = Compositor(640, SIDE, circular_fov=False)        # the square spans columns 64..575; 1 px strokes
    image = np.ones((64, 64), np.float32)
    bare = comp.compose(image, Overlay(), now=0.0)
    core, outline = static_text_masks(comp, TITLE)
    over_image = np.zeros(core.shape, bool)
    over_image[:, 64:576] = True
    in_box = np.zeros(core.shape, bool)
    for x0, y0, x1, y1 in (line.box for line in comp._static_texts(TITLE)):
        in_box[y0:y1, x0:x1] = True
    # The outline's own pixels, clear of the text, inside the line's box.
    ring = (outline > 200) & (core == 0) & over_image & in_box
    text = core > 200                                       # well inside the strokes, over the field and the black bar
    assert ring.sum() > 50 and text.sum() > 100
    for _ in range(2):                                       # drawn afresh, then from the cache
        frame = comp.compose(image, TITLE, now=0.0)
        assert (frame[ring] == 0).all(), "the outline is black where it crosses the white field"
        assert (frame[text] > 200).all(), "the title itself is white"
        # Inside the boxes, clear of text and outline, the white field shows through.
        assert (frame[in_box & over_image & (outline == 0) & (core == 0)] == 255).all()
        # Outside the title's and the label's boxes the screen is the one without them.
        assert np.array_equal(frame[~in_box], bare[~in_box])


@pytest.mark.parametrize("size", [(1280, 1024), (1920, 1080)])
def test_the_corner_text_outline_shows_on_a_full_size_monitor(size):
    """On a full-size monitor (2 px strokes, so a 2 px border) the corner text over a white
    field has its black ring all round: every pixel within 2 px of the stroke is black under
    the text's own coverage, and the ring outside the stroke is about twice the stroke's edge."""
    comp = Compositor(*size, circular_fov=False)
    assert comp.thickness == 2
    core, outline = static_text_masks(comp, TITLE)
    stroke = core >= 128
    edge = stroke & ~cv2.erode(stroke.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    assert ((outline == 255) & ~stroke).sum() > 0.6 * 2 * edge.sum(), "a ring 2 px wide outside the strokes"
    frame = comp.compose(np.ones((64, 64), np.float32), TITLE, now=0.0)
    over_image = np.zeros(core.shape, bool)
    over_image[:, comp.x0:comp.x0 + comp.side] = True
    ring = (outline == 255) & (core == 0) & over_image
    assert ring.sum() > 500
    assert (frame[ring] == 0).all(), "the outline is black where it crosses the white field"
    near = (outline == 255) & over_image                     # the text laid over its black ring
    assert np.array_equal(frame[near], np.repeat(core[near][:, None], 3, axis=1)), "white text on black"


def test_the_live_and_hold_markers_sit_on_their_boxes():
    comp = Compositor(640, SIDE)
    dark = np.zeros((64, 64), np.float32)
    for live, fill in ((True, (255, 214, 0)), (False, (60, 60, 60))):
        (marker,) = [t for t in comp.text_layout(Overlay(live=live), now=0.0) if t.text in ("LIVE", "HOLD")]
        assert marker.text == ("LIVE" if live else "HOLD")
        x0, y0, x1, y1 = marker.box
        frame = comp.compose(dark, Overlay(live=live), now=0.0)
        corner = np.zeros(frame.shape[:2], bool)
        corner[SIDE // 2:, 320:] = True                       # the bottom-right quarter (grey text edges elsewhere)
        rows, cols = np.nonzero(np.all(frame == fill, axis=2) & corner)
        # A filled box half a margin wider than the text's box each side, as tall as it.
        assert (cols.min(), cols.max()) == (x0 - comp.margin // 2, x1 + comp.margin // 2)
        assert (rows.min(), rows.max()) == (y0, y1)


# The field's circle on 640 x 512: centre (320, 256) (319.5 and 255.5 rounded half to even),
# radius 256; on 640 x 511: centre (319, 255), radius 255.5 (256 rounded half to even). The ring
# is two 1 px strokes inside the edge, three strokes wide.
@pytest.mark.parametrize("size, centre, radius", [((640, 512), (320, 256), 254), ((640, 511), (319, 255), 254)])
def test_the_saved_ring_is_centred_on_the_field_two_strokes_inside_its_edge(size, centre, radius):
    comp = Compositor(*size)
    assert comp.thickness == 1
    dark = np.zeros((64, 64), np.float32)
    plain = comp.compose(dark, Overlay(), now=0.0)
    flash = comp.compose(dark, Overlay(saved_flash=True), now=0.0)
    expected = plain.copy()
    cv2.circle(expected, centre, radius, WHITE, 3, cv2.LINE_AA)
    keep = np.ones(plain.shape[:2], bool)
    for x0, y0, x1, y1 in (t.box for t in comp.text_layout(Overlay(saved_flash=True), now=0.0)):
        keep[max(y0 - 4, 0):y1 + 4, max(x0 - 4, 0):x1 + 4] = False
    banner = [b for b in boxes(flash, GREEN)]
    assert len(banner) == 1
    keep[banner[0][0] - 1:banner[0][1] + 2, :] = False       # the IMAGE SAVED banner's rows
    assert keep.sum() > 0.8 * keep.size
    assert np.array_equal(flash[keep], expected[keep])


def test_without_a_time_the_alarm_flashes_on_the_monotonic_clock():
    import time
    comp = Compositor(640, SIDE)
    frame = comp.compose(np.zeros((64, 64), np.float32), Overlay(alarm=True, alarm_since=time.monotonic()))
    assert np.all(frame == RED, axis=2).sum() > 1000         # lit in the first half second of its onset


def test_a_tall_detector_is_centred_and_its_blades_use_its_displayed_width():
    comp = Compositor(640, SIDE, circular_fov=False)
    # 64 rows x 32 columns: 512 px high, 256 px wide, columns 128..383 of the square.
    square = comp._image_square(np.ones((64, 32), np.float32), Overlay(fov_mm=300.0, collimation_mm=(150.0, 100.0)))
    lit = np.flatnonzero(square[256] > 0)
    assert (lit.min(), lit.max()) == (128, 383)
    # 256 px span 300 mm: 150 mm is 128 px across, 100 mm 85.3 px down (edges 192..320, 213..299).
    dim = (3 * 255) // 10
    assert square[256, 200] == 255 and square[256, 185] == dim and square[256, 315] == 255 and square[256, 325] == dim
    assert square[220, 256] == 255 and square[205, 256] == dim and square[295, 256] == 255 and square[305, 256] == dim


def test_a_wide_detector_of_any_aspect_is_letterboxed_in_the_middle():
    comp = Compositor(640, SIDE, circular_fov=False)
    square = comp._image_square(np.ones((48, 64), np.float32), Overlay())    # 384 px high: rows 64..447
    lit = np.flatnonzero(square[:, 256] > 0)
    assert (lit.min(), lit.max()) == (64, 447)


def test_a_larger_image_is_averaged_down_and_a_smaller_one_interpolated_up():
    comp = Compositor(640, SIDE, circular_fov=False)
    # One-pixel columns, black and white, three to a screen pixel: an area average shows 1/3 or 2/3
    # grey; sampling would show black and white.
    stripes = (np.arange(3 * SIDE) % 2).astype(np.float32)[None, :].repeat(3 * SIDE, axis=0)
    square = comp._image_square(stripes, Overlay())
    assert set(np.unique(square[256, 8:-8])) <= {85, 170}
    # Two pixels, black and white, up to 512: a linear ramp across the middle half, flat at the ends.
    square = comp._image_square(np.array([[0.0, 1.0]], np.float32).repeat(2, axis=0), Overlay())
    row = square[256].astype(int)
    assert row[0] == 0 and row[-1] == 255 and (np.diff(row) >= 0).all()
    middle = row[128:384]
    assert np.abs(middle - (np.arange(128, 384) + 0.5 - 128) * 255 / 256).max() <= 1.5


@pytest.mark.parametrize("live, fill, ink", [(True, (255, 214, 0), (0, 0, 0)), (False, (60, 60, 60), (255, 255, 255))])
def test_the_live_and_hold_markers_are_lettered_in_the_bold_face(live, fill, ink):
    # Worked from the layout's rules on 640 x 512, not read from it: a line pitch of 512 / 30 -> 17
    # px, thickness 1 (the marker's 2), margin 6 and the marker's inset 3, so it ends 9 px in from
    # the right edge; it stands on the dose line's baseline, a margin (6 px) above that line's
    # depth (its text in Hershey simplex 0.55 of a line, 9 px, high); its letters are Hershey
    # duplex 0.85 of a line (14 px) high, in a box padded 3 px, widened half a margin.
    comp = Compositor(640, SIDE)
    text = "LIVE" if live else "HOLD"
    font = cv2.FONT_HERSHEY_DUPLEX
    scale = cv2.getFontScaleFromHeight(font, 14, 2)
    (w, h), base = cv2.getTextSize(text, font, scale, 2)
    _, dose_depth = cv2.getTextSize("DAP  0.000 Gy cm", FONT, cv2.getFontScaleFromHeight(FONT, 9, 1), 1)
    org = (640 - 9 - w, SIDE - 6 - dose_depth)
    x0, y0, x1, y1 = org[0] - 3, org[1] - h - 3, org[0] + w + 3, org[1] + base + 3
    expected = np.zeros((SIDE, 640, 3), np.uint8)
    cv2.rectangle(expected, (x0 - 3, y0), (x1 + 3, y1), fill, thickness=-1)
    cv2.putText(expected, text, org, font, scale, ink, 2, cv2.LINE_AA)
    frame = comp.compose(np.zeros((64, 64), np.float32), Overlay(live=live), now=0.0)
    box = (slice(y0, y1 + 1), slice(x0 - 3, x1 + 4))
    assert np.array_equal(frame[box], expected[box])


def test_before_the_first_image_the_field_is_dark_grey_and_says_starting_in_its_middle():
    # On 640 x 512 the field is centred on (320, 256); the label is grey Hershey duplex in the
    # marker's size (14 px high, thickness 2), centred there, over the field's grey 24.
    comp = Compositor(640, SIDE)
    font = cv2.FONT_HERSHEY_DUPLEX
    scale = cv2.getFontScaleFromHeight(font, 14, 2)
    (w, h), base = cv2.getTextSize("STARTING", font, scale, 2)
    org = (round(320 - w / 2), round(256 + h / 2))
    expected = np.full((SIDE, 640, 3), 24, np.uint8)
    cv2.putText(expected, "STARTING", org, font, scale, (170, 170, 170), 2, cv2.LINE_AA)
    frame = comp.compose(None, Overlay(), now=0.0)
    around = (slice(org[1] - h - 6, org[1] + base + 6), slice(org[0] - 6, org[0] + w + 6))
    assert np.array_equal(frame[around], expected[around])
    assert (frame[around] == 170).all(axis=2).sum() > 50          # the letters are there, in grey
    # The field is the circle of radius 256 about the square's centre (319.5, 255.5 in pixel
    # centres): grey inside, black beyond it in the square's corners, where no text lies.
    y, x = np.mgrid[0:SIDE, 64:576]
    r2 = (x - 319.5) ** 2 + (y - 255.5) ** 2
    square = frame[:, 64:576]
    corner = (r2 > 257.0 ** 2) & (y > 100) & (y < SIDE - 100)
    assert corner.sum() > 1000 and not square[corner].any()
    assert (square[(r2 < 250.0 ** 2) & (np.abs(y - 255.5) > 40)] == 24).all()


def test_the_fourth_warning_banner_reads_how_many_more_there_are():
    # Seven warnings: three shown and a fourth that stands for the other four (7 - 3), in letters
    # of the same width as any other count, so its pixels, not its box, tell the number.
    comp = Compositor(640, SIDE)
    frame = comp.compose(np.zeros((64, 64), np.float32), Overlay(warnings=[f"warning {k}" for k in range(7)]),
                         now=0.75)
    top, bottom, left, right = boxes(frame, AMBER)[3]
    drawn = drawn_banner(comp, "... AND 4 MORE WARNINGS", top, AMBER, BLACK)
    assert np.array_equal(frame[top:bottom + 1, left:right + 1], drawn[top:bottom + 1, left:right + 1])


@pytest.mark.parametrize("after_s, lit", [
    (0.0, True), (0.4, True), (0.5, False), (0.9, False), (1.2, True), (1.5, False),
])
def test_the_alarm_banner_flashes_half_of_each_second_from_the_alarms_onset(after_s, lit):
    # The alarm began at 2.25 s on the compose clock (binary-exact, so 0.5 s after it is exactly
    # half a period): lit for [0, 0.5) s of each 1 s period after it, dark for [0.5, 1). A flash
    # timed from 0 instead of the onset would be dark 0.4 s after it (2.65 % 1) and lit 0.9 s after.
    comp = Compositor(640, SIDE)
    overlay = Overlay(alarm=True, fluoro_time_s=301.0, alarm_since=2.25)
    frame = comp.compose(np.zeros((64, 64), np.float32), overlay, now=2.25 + after_s)
    assert (len(boxes(frame, RED)) == 1) is lit


def test_a_tall_detector_larger_than_the_square_is_averaged_down():
    # 2048 x 1024 (rows x columns) into the 512 px square: shown 256 x 512, a quarter each way, so
    # every screen pixel averages 4 columns of which one is white: 255 / 4 = 63.75 -> 64 (sampling
    # between pixels instead would give 0 or 255).
    comp = Compositor(640, SIDE, circular_fov=False)
    image = np.zeros((2048, 1024), np.float32)
    image[:, ::4] = 1.0
    square = comp._image_square(image, Overlay())
    assert (square[:, 128:384] == 64).all() and (square[:, :128] == 0).all() and (square[:, 384:] == 0).all()


def test_the_corner_text_starts_a_margin_in_from_the_left_edge():
    # 640 x 512: a margin of max(6, 17 // 3) = 6 px; the left corners' lines begin there.
    lines = Compositor(640, SIDE).text_layout(Overlay(case="x"), now=0.0)
    assert {t.org[0] for t in lines if t.text.startswith(("CASE", "DAP", "AIR KERMA", "FLUORO"))} == {6}


def test_a_line_that_changes_at_the_same_place_shows_its_new_text_not_the_cached_old():
    """The blend layers of a line are kept from frame to frame; a figure that changes in place
    (the dose rate ticking over) must show the new text: drawn after the old one at the same
    origin, scale and colour, it is exactly the new text's coverage on black within the border,
    and the old text's strokes that the new one does not cover show nothing of it."""
    from appliance.display.text import TextLine, draw_text
    canvas = np.full((80, 400, 3), 200, np.uint8)
    old = TextLine("DAP 1.23 Gy cm", (10, 50), 1.0, (255, 214, 0), FONT, 2, "2")
    new = TextLine("DAP 7.40 Gy cm", (10, 50), 1.0, (255, 214, 0), FONT, 2, "2")
    draw_text(canvas.copy(), old)
    got = canvas.copy()
    draw_text(got, new)
    core = text_coverage(canvas.shape[:2], [new])
    near = distance_to(core >= 128) <= 2
    on_black = np.rint(np.array(new.color, np.float64) * core[..., None] / 255.0)
    assert np.array_equal(got[near], on_black[near])
    gone = (text_coverage(canvas.shape[:2], [old]) >= 128) & (distance_to(core > 0) > 2 + 1e-3)
    assert gone.sum() > 20 and (got[gone] == 200).all()
