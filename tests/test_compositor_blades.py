"""Where the compositor draws the blades and fits the image, worked by hand: px per mm from the
displayed image's width and the field of view, shut blades, a field of view of 0, a sliver image."""

from __future__ import annotations

from appliance.display.compositor import Compositor, Overlay


def test_blade_opening_in_pixels_of_the_displayed_image():
    c = Compositor(640, 512)                       # a 512 px square, centre 256
    # 300 mm across 512 px: 150 x 75 mm open 256 x 128 px about the centre.
    assert c.blade_edges(Overlay(fov_mm=300.0, collimation_mm=(150.0, 75.0))) == (128, 192, 384, 320)
    # A non-square detector shown 256 px wide: the same 300 mm span 256 px, so the opening halves.
    assert c.blade_edges(Overlay(fov_mm=300.0, collimation_mm=(150.0, 75.0)), image_width_px=256) == (192, 224, 320, 288)
    # Shut blades are a closed slit at the centre; wider than the field is the whole square.
    assert c.blade_edges(Overlay(fov_mm=300.0, collimation_mm=(0.0, -5.0))) == (256, 256, 256, 256)
    assert c.blade_edges(Overlay(fov_mm=300.0, collimation_mm=(900.0, 900.0))) == (0, 0, 512, 512)
    # A tiny field still has blades; no field or fully open blades draw none.
    assert c.blade_edges(Overlay(fov_mm=1.0, collimation_mm=(0.5, 0.25))) == (128, 192, 384, 320)
    assert c.blade_edges(Overlay(fov_mm=0.0, collimation_mm=(10.0, 10.0))) is None
    assert c.blade_edges(Overlay(fov_mm=300.0, collimation_mm=None)) is None


def test_a_sliver_of_an_image_is_still_one_pixel_wide():
    c = Compositor(320, 256)
    assert c._fitted(1000, 1) == (1, 256)
    assert c._fitted(1, 1000) == (256, 1)
    assert c._fitted(120, 160) == (256, 192)
