"""The dose lines of the screen read back from the composed frame: the fluoroscopy time turns
yellow while the five-minute alarm sounds (and only then), and the air-kerma rate is shown
while exposing and not otherwise (IEC 60601-2-43 asks for the rate during irradiation).

Ground truth: the display's colours (YELLOW (255, 214, 0) for the alarm, white text otherwise)
counted in the pixels of the line's own box; the rate as the test sets it.
"""

from __future__ import annotations

import numpy as np
import pytest

from appliance.display.compositor import Compositor, Overlay

YELLOW = np.array([255, 214, 0])


def fluoro_line_pixels(comp: Compositor, overlay: Overlay) -> np.ndarray:
    (line,) = [t for t in comp.text_layout(overlay, now=0.0) if t.text.startswith("FLUORO")]
    x0, y0, x1, y1 = line.box
    frame = comp.compose(np.full((64, 64), 0.5, np.float32), overlay, now=0.0)
    return frame[y0:y1, x0:x1].reshape(-1, 3).astype(int)


@pytest.mark.parametrize("size", [(1920, 1080), (1280, 1024)])
def test_fluoroscopy_time_is_yellow_while_the_alarm_sounds(size):
    comp = Compositor(*size)
    quiet = fluoro_line_pixels(comp, Overlay(fluoro_time_s=290.0))
    sounding = fluoro_line_pixels(comp, Overlay(fluoro_time_s=300.0, alarm=True, alarm_since=0.0))
    yellow_quiet = np.all(np.abs(quiet - YELLOW) <= 2, axis=1).sum()
    yellow_sounding = np.all(np.abs(sounding - YELLOW) <= 2, axis=1).sum()
    assert yellow_quiet == 0
    assert yellow_sounding > 50, yellow_sounding
    # Quiet, the same glyphs are white.
    assert np.all(quiet >= 250, axis=1).sum() > 50


def air_kerma_line(overlay: Overlay) -> str:
    (line,) = [t.text for t in Compositor(1920, 1080).text_layout(overlay, now=0.0) if t.text.startswith("AIR KERMA")]
    return line


def test_air_kerma_rate_is_shown_while_exposing_only():
    assert air_kerma_line(Overlay(live=True, air_kerma_mgy=12.0, air_kerma_rate_mgy_per_min=8.04)).endswith("8.0 mGy/min")
    resting = air_kerma_line(Overlay(live=False, air_kerma_mgy=12.0, air_kerma_rate_mgy_per_min=0.0))
    assert "mGy/min" not in resting and resting.endswith("mGy")
