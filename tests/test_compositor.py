"""The compositor: field-of-view geometry, collimation, inversion and markers against hand-worked values."""

from __future__ import annotations

import numpy as np
import pytest

from appliance.display.compositor import ALARM_FLASH_PERIOD_S, COLLIMATED_BRIGHTNESS, Compositor, Overlay
from appliance.display.text import dose_number, fluoro_time_clock, fluoro_time_minutes

SCREENS = [(1920, 1080), (1280, 1024)]


def plain_overlay(**kw) -> Overlay:
    values = dict(live=False, zoom=1, fov_mm=300.0, collimation_mm=None, fluoro_time_s=0.0, air_kerma_mgy=0.0,
                  dap_gy_cm2=0.0, mode="", alarm=False, saved_flash=False, invert=False, breath_hold=False,
                  case="", operator="", fluoroscope="", warnings=[], fps=None)
    values.update(kw)
    return Overlay(**values)


def full_overlay(**kw) -> Overlay:
    values = dict(live=True, zoom=3, fov_mm=170.0, collimation_mm=(120.0, 90.0), fluoro_time_s=6012.0,
                  air_kerma_mgy=1234.5, dap_gy_cm2=98.76, mode="pulsed-7.5", invert=True, breath_hold=True,
                  case="Child torso VCUG, late voiding phase", operator="Dr. A. Long-Surname-Trainee",
                  fluoroscope="Generic image-intensifier C-arm (room 4)", fps=14.9)
    values.update(kw)
    return plain_overlay(**values)


def text_mask(comp: Compositor, overlay: Overlay) -> np.ndarray:
    """True where some overlay text (with its outline) may be drawn."""
    mask = np.zeros((comp.height, comp.width), bool)
    for t in comp.text_layout(overlay, now=0.0):
        x0, y0, x1, y1 = t.box
        m = comp.margin
        mask[max(y0 - m, 0):y1 + m, max(x0 - m, 0):x1 + m] = True
    return mask


@pytest.mark.parametrize("size", SCREENS)
def test_image_fills_the_circle_inscribed_in_the_centred_square(size):
    width, height = size
    comp = Compositor(width, height)
    overlay = plain_overlay()
    frame = comp.compose(np.ones((256, 256), np.float32), overlay, now=0.0)
    assert frame.shape == (height, width, 3) and frame.dtype == np.uint8
    # Independent geometry: the square is height x height centred horizontally; the circle has radius height / 2.
    cx, cy, r = width / 2.0, height / 2.0, height / 2.0
    yy, xx = np.mgrid[0:height, 0:width]
    d = np.hypot(xx + 0.5 - cx, yy + 0.5 - cy)
    free = ~text_mask(comp, overlay)
    inside = (d < r - 1.5) & free
    outside = (d > r + 1.5) & free
    assert inside.sum() > 0.7 * np.pi * r * r and outside.sum() > 0.1 * width * height
    assert (frame[inside] == 255).all()
    assert (frame[outside] == 0).all()


def test_rectangular_field_for_flat_panels():
    comp = Compositor(1280, 1024, circular_fov=False)
    frame = comp.compose(np.ones((64, 64), np.float32), plain_overlay(), now=0.0)
    # The corner of the square just right of the left letterbox bar, below the top-left text, is image.
    assert (frame[400, 128 + 2] == 255).all() and (frame[400, 128 - 2] == 0).all()


@pytest.mark.parametrize("size", SCREENS)
def test_columns_and_rows_keep_their_orientation(size):
    width, height = size
    comp = Compositor(width, height)
    n = 64
    ramp = np.tile(np.linspace(0.0, 1.0, n, dtype=np.float32), (n, 1))   # value grows with the column
    x0 = (width - height) // 2
    s = height
    for image, along_rows in ((ramp, False), (ramp.T.copy(), True)):
        frame = comp.compose(image, plain_overlay(), now=0.0)
        for k in range(s // 8, s - s // 8, s // 16):
            # Screen pixel centre k + 0.5 of the square samples image coordinate (k + 0.5) * n / s - 0.5.
            u = np.clip((k + 0.5) * n / s - 0.5, 0, n - 1)
            expected = 255.0 * u / (n - 1)
            got = frame[k, x0 + s // 2, 0] if along_rows else frame[s // 2, x0 + k, 0]
            assert abs(int(got) - expected) <= 3, (k, got, expected)


def test_invert_is_a_label_the_image_arrives_inverted():
    """Polarity has one owner, the renderer's display LUT: the compositor shows the INVERT
    label but leaves the pixels alone, so the image is never inverted twice."""
    comp = Compositor(1280, 1024)
    img = np.full((32, 32), 0.2, np.float32)
    plain = comp.compose(img, plain_overlay(), now=0.0)
    labelled = comp.compose(img, plain_overlay(invert=True), now=0.0)
    assert abs(int(plain[512, 640, 0]) - 51) <= 1      # 0.2 x 255
    assert (labelled[512, 640] == plain[512, 640]).all()
    assert (labelled[512, 64] == 0).all()               # letterbox stays black
    assert (plain[512, 640] == plain[512, 640, 0]).all(), "the image is grey"
    assert (labelled != plain).any(), "the INVERT label is drawn"


def test_out_of_range_values_saturate():
    comp = Compositor(640, 480)
    img = np.full((16, 16), 3.0, np.float32)
    img[:, :8] = -2.0
    frame = comp.compose(img, plain_overlay(), now=0.0)
    assert frame[240, 320 - 60, 0] == 0 and frame[240, 320 + 60, 0] == 255


@pytest.mark.parametrize("size", SCREENS)
def test_collimation_darkens_outside_the_blade_opening(size):
    width, height = size
    comp = Compositor(width, height)
    # Opening 150 x 75 mm in a 300 mm field: half and a quarter of the image width.
    overlay = plain_overlay(fov_mm=300.0, collimation_mm=(150.0, 75.0))
    frame = comp.compose(np.ones((128, 128), np.float32), overlay, now=0.0)
    cx, cy, half = width // 2, height // 2, height / 2.0
    dim = round(255 * COLLIMATED_BRIGHTNESS)
    for frac, inside in ((0.0, True), (0.45, True), (0.55, False), (0.9, False)):
        value = int(frame[cy, cx + round(frac * half), 0])
        assert abs(value - (255 if inside else dim)) <= 1, ("horizontal", frac, value)
        value = int(frame[cy, cx - round(frac * half), 0])
        assert abs(value - (255 if inside else dim)) <= 1, ("horizontal left", frac, value)
    for frac, inside in ((0.2, True), (0.3, False), (0.8, False)):
        value = int(frame[cy + round(frac * half), cx, 0])
        assert abs(value - (255 if inside else dim)) <= 1, ("vertical", frac, value)
    # Fully open blades, or an opening wider than the field, leave the image untouched.
    wide = comp.compose(np.ones((128, 128), np.float32), plain_overlay(collimation_mm=(400.0, 400.0)), now=0.0)
    assert wide[cy, cx + round(0.9 * half), 0] == 255


def test_alarm_banner_flashes_red():
    comp = Compositor(1920, 1080)
    img = np.full((64, 64), 0.5, np.float32)
    overlay = plain_overlay(alarm=True, fluoro_time_s=301.0)

    def red_pixels(frame):
        return int(((frame[..., 0] >= 200) & (frame[..., 1] <= 40) & (frame[..., 2] <= 40)).sum())

    on = comp.compose(img, overlay, now=10.0 + 0.1 * ALARM_FLASH_PERIOD_S)
    off = comp.compose(img, overlay, now=10.0 + 0.6 * ALARM_FLASH_PERIOD_S)
    assert red_pixels(on) > 5000
    assert red_pixels(off) == 0
    assert red_pixels(comp.compose(img, plain_overlay(), now=10.1)) == 0
    # The flash runs from the alarm's onset: lit at once, dark half a period later, lit again.
    onset = 17.37
    started = plain_overlay(alarm=True, fluoro_time_s=300.0, alarm_since=onset)
    assert red_pixels(comp.compose(img, started, now=onset)) > 5000
    assert red_pixels(comp.compose(img, started, now=onset + 0.6 * ALARM_FLASH_PERIOD_S)) == 0
    assert red_pixels(comp.compose(img, started, now=onset + 1.1 * ALARM_FLASH_PERIOD_S)) > 5000


def test_live_marker_is_yellow_and_hold_is_not():
    comp = Compositor(1280, 1024)
    img = np.zeros((64, 64), np.float32)

    def yellow_in_corner(frame):
        corner = frame[1024 * 3 // 4:, 1280 * 3 // 4:]
        return int(((corner[..., 0] > 230) & (corner[..., 1] > 190) & (corner[..., 1] < 235) & (corner[..., 2] < 40)).sum())

    assert yellow_in_corner(comp.compose(img, plain_overlay(live=True), now=0.0)) > 500
    assert yellow_in_corner(comp.compose(img, plain_overlay(live=False), now=0.0)) == 0


def test_saved_flash_rings_the_field_of_view():
    comp = Compositor(1280, 1024)
    img = np.zeros((64, 64), np.float32)
    plain = comp.compose(img, plain_overlay(), now=0.0)
    flash = comp.compose(img, plain_overlay(saved_flash=True), now=0.0)
    # On the horizontal diameter, just inside the circle's left edge.
    band = slice(128 + 2, 128 + 4 * comp.thickness + 2)
    assert (plain[512, band] == 0).all()
    assert (flash[512, band] == 255).any()


def test_starting_screen_before_the_first_frame():
    comp = Compositor(1920, 1080)
    frame = comp.compose(None, plain_overlay(), now=0.0)
    assert (frame[540, 960 - 300] == 24).all(), "dim field of view"
    assert frame[520:560, 900:1020].max() > 100, "the word STARTING in the middle"


@pytest.mark.parametrize("size", SCREENS)
def test_text_stays_on_screen_without_lines_overlapping(size):
    comp = Compositor(*size)
    boxes = [t.box for t in comp.text_layout(full_overlay(), now=0.0)]
    assert len(boxes) >= 11
    for x0, y0, x1, y1 in boxes:
        assert 0 <= x0 < x1 <= size[0] and 0 <= y0 < y1 <= size[1]
    for i, a in enumerate(boxes):
        for b in boxes[i + 1:]:
            overlap = min(a[2], b[2]) > max(a[0], b[0]) and min(a[3], b[3]) > max(a[1], b[1])
            assert not overlap, (a, b)
    # Legible from the operator's position: capital letters at least 1/60 of the screen height.
    assert comp.line * 0.55 >= size[1] / 60


def test_every_overlay_drawn_at_once_and_each_frame_is_a_new_array():
    comp = Compositor(1280, 1024)
    img = np.random.default_rng(1).random((200, 200), dtype=np.float32)
    overlay = full_overlay(alarm=True, saved_flash=True, warnings=[f"warning {i}" for i in range(7)])
    a = comp.compose(img, overlay, now=0.1)
    b = comp.compose(img, overlay, now=0.1)
    assert a is not b and np.array_equal(a, b)
    a[...] = 0
    assert comp.compose(img, overlay, now=0.1).max() == 255


def test_clock_minutes_and_dose_formats():
    assert fluoro_time_clock(0) == "00:00"
    assert fluoro_time_clock(59.99) == "00:59"
    assert fluoro_time_clock(157.9) == "02:37"
    assert fluoro_time_clock(300) == "05:00"
    assert fluoro_time_clock(6000) == "100:00"
    assert fluoro_time_minutes(157.9) == "2.6 min"     # 2.63 min, completed tenths
    assert fluoro_time_minutes(5.99) == "0.0 min"
    assert fluoro_time_minutes(6.0) == "0.1 min"
    assert fluoro_time_minutes(300.0) == "5.0 min"
    assert fluoro_time_minutes(3599.0) == "59.9 min"
    assert dose_number(0.0) == "0.000"
    assert dose_number(0.8764) == "0.876"
    assert dose_number(1.234) == "1.23"
    assert dose_number(12.34) == "12.3"
    assert dose_number(123.4) == "123"
    assert dose_number(4321.0) == "4321"


def test_bad_sizes_are_refused():
    with pytest.raises(ValueError):
        Compositor(10, 10)
    comp = Compositor(640, 480)
    with pytest.raises(ValueError, match="rows, cols"):
        comp.compose(np.zeros((4, 4, 3), np.float32), plain_overlay())


def test_display_benchmark_runs_and_writes_its_screens(tmp_path, capsys):
    from appliance.cli import main
    assert main(["bench", "display", "--frames", "2", "--image-size", "64", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "compose 1920x1080:" in out and "compose 1280x1024:" in out
    assert all(f"{bpp} bpp 1920x1080: show with one copy" in out for bpp in (16, 24, 32))
    import cv2
    assert cv2.imread(str(tmp_path / "compose-1280x1024.png")).shape == (1024, 1280, 3)


def test_a_wide_detector_keeps_its_aspect_ratio():
    comp = Compositor(1280, 1024, circular_fov=False)
    frame = comp.compose(np.ones((32, 64), np.float32), plain_overlay(), now=0.0)
    # 64 columns fill the 1024-pixel square's width; 32 rows fill half its height, centred.
    cx, cy = 640, 512
    assert (frame[cy + 200, cx] == 255).all() and (frame[cy - 200, cx] == 255).all()
    assert (frame[cy + 300, cx] == 0).all() and (frame[cy - 300, cx] == 0).all()
    assert (frame[cy, 128 + 2] == 255).all() and (frame[cy, 1280 - 128 - 3] == 255).all()
    # Collimation keeps one scale for both blade pairs: 1024 pixels span the 300 mm wide field, so
    # 150 mm is 512 pixels across and 100 mm is 341 pixels down (edges at +-256 and +-171 from the centre).
    coll = comp.compose(np.ones((32, 64), np.float32), plain_overlay(fov_mm=300.0, collimation_mm=(150.0, 100.0)), now=0.0)
    dim = round(255 * COLLIMATED_BRIGHTNESS)
    assert coll[cy, cx + 240, 0] == 255 and abs(int(coll[cy, cx + 270, 0]) - dim) <= 1
    assert coll[cy + 160, cx, 0] == 255 and abs(int(coll[cy + 185, cx, 0]) - dim) <= 1


def test_corner_text_keeps_its_dark_outline_over_a_bright_image():
    comp = Compositor(1280, 1024)
    overlay = plain_overlay(case="Child torso VCUG, a long case title that runs into the image")
    frame = comp.compose(np.ones((64, 64), np.float32), overlay, now=0.0)
    line = comp.text_layout(overlay, now=0.0)[0]
    x0, y0, x1, y1 = line.box
    # Where the title crosses the white field of view, its outline is drawn black over the image.
    cx, cy, r = 640, 512, 512
    yy, xx = np.mgrid[y0:y1, x0:x1]
    over_image = np.hypot(xx + 0.5 - cx, yy + 0.5 - cy) < r - 2
    assert over_image.sum() > 100
    region = frame[y0:y1, x0:x1]
    assert (region[over_image] < 60).all(axis=-1).sum() > 50
