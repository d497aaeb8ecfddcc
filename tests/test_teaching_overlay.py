"""The teaching overlay: shot counter and current task in the dose corner, and the cue banner
after a save: on screen, not overlapping the other text, green when met and amber when not."""

import numpy as np
import pytest

from appliance.display.compositor import Compositor, Overlay

SCREENS = [(1920, 1080), (1280, 1024)]


def overlay(**kw) -> Overlay:
    values = dict(live=True, zoom=2, fov_mm=170.0, collimation_mm=(120.0, 90.0), fluoro_time_s=95.0,
                  air_kerma_mgy=12.5, dap_gy_cm2=1.2, mode="pulsed-7.5", case="Child torso - VCUG and breathing",
                  operator="Ada Lovelace", fluoroscope="Generic II C-arm", shots=17,
                  task="task 5/5: post-void bladder and kidneys")
    values.update(kw)
    return Overlay(**values)


@pytest.mark.parametrize("size", SCREENS)
def test_task_and_shots_are_on_screen_without_overlap(size):
    comp = Compositor(*size)
    texts = comp.text_layout(overlay(), now=0.0)
    names = [t.text for t in texts]
    assert "SHOTS  17" in names and "TASK 5/5: POST-VOID BLADDER AND KIDNEYS" in names
    boxes = [t.box for t in texts]
    for x0, y0, x1, y1 in boxes:
        assert 0 <= x0 < x1 <= size[0] and 0 <= y0 < y1 <= size[1]
    for i, a in enumerate(boxes):
        for b in boxes[i + 1:]:
            assert not (min(a[2], b[2]) > max(a[0], b[0]) and min(a[3], b[3]) > max(a[1], b[1])), (a, b)
    # The task sits above the shot counter, both above the dose lines (y grows downward).
    y = {t.text: t.org[1] for t in texts}
    assert y["TASK 5/5: POST-VOID BLADDER AND KIDNEYS"] < y["SHOTS  17"] < min(v for k, v in y.items() if k.startswith("DAP"))


def test_no_shot_counter_or_task_when_not_asked():
    names = [t.text for t in Compositor(1280, 1024).text_layout(overlay(shots=None, task=""), now=0.0)]
    assert not any(n.startswith(("SHOTS", "TASK")) for n in names)


def _banner_pixels(frame, colour):
    r, g, b = colour
    band = frame[150:450]
    return int(((abs(band[..., 0].astype(int) - r) < 8) & (abs(band[..., 1].astype(int) - g) < 8)
                & (abs(band[..., 2].astype(int) - b) < 8)).sum())


def test_cue_is_green_when_met_and_amber_when_not():
    comp = Compositor(1280, 1024)
    img = np.full((64, 64), 0.2, np.float32)
    plain = comp.compose(img, overlay(), now=0.0)
    met = comp.compose(img, overlay(saved_flash=True, cue="task met: early filling AP"), now=0.0)
    not_met = comp.compose(img, overlay(cue="not yet: not collimated"), now=0.0)
    green, amber = (0, 200, 80), (255, 170, 0)
    assert _banner_pixels(plain, green) == 0 and _banner_pixels(plain, amber) == 0
    saved_only = _banner_pixels(comp.compose(img, overlay(saved_flash=True), now=0.0), green)
    # The task-met banner under the image-saved one, wider than it; the reasons in amber.
    assert saved_only > 3000 and _banner_pixels(met, green) > 2.2 * saved_only
    assert _banner_pixels(not_met, amber) > 3000 and _banner_pixels(not_met, green) == 0
