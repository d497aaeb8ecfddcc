"""What a frame at an unchanged pose still asks of the device: the exposure control's sample of
the cached integrals is gathered once per cast phase and blended on the host, checked against
closed-form chords and against a control that gathers afresh."""

import numpy as np
import pytest

# The projection cache's own scene: its grid and its oblique pose.
from test_projection_cache import POSE, SHAPE, SPACING

from appliance.config.case import Contrast, Materials
from appliance.patient.materials import density_model
from appliance.xray.bench import flat_profile
from appliance.xray.casting import BlendedLines
from appliance.xray.projection_cache import ProjectionCache
from appliance.xray.renderer import Renderer, View, zoomed_K
from appliance.xray.truth.analytic import box_chords, box_volume, pixel_rays_ct


@pytest.fixture(scope="module")
def renderer():
    return Renderer(flat_profile(96), Materials(contrast_min_hu=2500), Contrast(concentration_mg_per_ml=150),
                    device="cpu")


def two_phases():
    """A box of water filling most of the grid, and the same box 'breathed' 3-4 voxels along two
    axes: both cover the exposure control's measuring field."""
    a, lo_a, hi_a = box_volume(SHAPE, SPACING, (2, 2, 2), (45, 45, 33))
    b, lo_b, hi_b = box_volume(SHAPE, SPACING, (2, 5, 6), (45, 45, 37))
    return (a, lo_a, hi_a), (b, lo_b, hi_b)


class CountingKernel:
    """The real gather kernel, counting its launches."""

    def __init__(self, kernel):
        self.kernel, self.calls = kernel, 0

    def __call__(self, *args, **kwargs):
        self.calls += 1
        return self.kernel(*args, **kwargs)


def test_cached_frames_gather_the_control_sample_once_per_phase_and_blend_it_as_the_chords(renderer, monkeypatch):
    (a, lo_a, hi_a), (b, lo_b, hi_b) = two_phases()
    pa, pb = renderer.prepare(a), renderer.prepare(b)
    gather = CountingKernel(renderer.caster._gather)
    monkeypatch.setattr(renderer.caster, "_gather", gather)
    assert renderer.fluoroscope.abc.enabled and renderer.fluoroscope.abc.curve     # the control reads its sample
    beam = renderer.caster.beam(1, None, False)
    rows, cols = renderer.shape
    s, d = pixel_rays_ct(zoomed_K(renderer.fluoroscope, 1), POSE, rows, cols)
    chord_a, chord_b = (box_chords(s, d, lo, hi).ravel()[beam.sample] for lo, hi in ((lo_a, hi_a), (lo_b, hi_b)))
    water = density_model(renderer.materials).offset[1]        # g/cm^3 of 0 HU
    cache = ProjectionCache(renderer)
    view = View(quantity="display", noise=False)
    frames = {}
    for w in (0.0, 0.3, 1.0, 0.3):
        lines, _ = cache._cached_cast(pa, POSE, 1, None, (pb, w), True, False)
        sample = renderer.caster.sample_lines(lines, beam)
        truth = water * ((1.0 - w) * chord_a + w * chord_b)        # g/cm^3 * mm of soft tissue
        deep = truth > 10.0 * water
        assert deep.sum() > 100
        rel = np.abs(sample[deep, 1] - truth[deep]) / truth[deep]
        assert np.median(rel) < 0.01, w
        frames[w] = cache.render(pa, POSE, view, blend=(pb, w))
    assert gather.calls == 2 and cache.counts.casts == 2        # one gather per phase, none per frame
    assert abs(frames[0.0].attenuation - frames[1.0].attenuation) > 0.01       # the control follows the blend
    # The same frames with the sample gathered on the device at each (the integrals' buffers
    # handed over without their host samples): the same technique.
    for w, frame in frames.items():
        lines, mask = cache._cached_cast(pa, POSE, 1, None, (pb, w), True, False)
        bare = BlendedLines(lines.a, lines.b, lines.w)
        fresh = renderer.render(pa, POSE, view, blend=(pb, w), cast=lambda *_, bare=bare, mask=mask: (bare, mask))
        assert (fresh.kvp, fresh.ma) == (frame.kvp, frame.ma)
        assert fresh.exposure_factor == pytest.approx(frame.exposure_factor, rel=1e-6)
        assert fresh.attenuation == pytest.approx(frame.attenuation, rel=1e-6)
