"""The demo's breathing-pair check: the dome's motion read from two images, against the
tendon's descent through the pinhole (SID/SOD).

Ground truth: images drawn here with a soft edge at known positions (the measurement must
return the shift drawn, whatever the prediction says), and the closed-form magnification
descent x SID / z of the apex over the pixel pitch (the prediction, up to the intensifier's
small distortion near the centre of the field)."""

from pathlib import Path

import numpy as np
import pytest

from appliance.config import load_appliance
from appliance.config.base import matrix
from appliance.daemon.breath_pair import builtin_apex, dome_shift, pair_lines
from appliance.daemon.parts import rendered_fluoroscope
from appliance.daemon.snapshots import KeptFrame
from appliance.tracking.trajectory import pose_from_angles

REPO = Path(__file__).resolve().parents[1]
#: The demo path's pose over the right dome (configs/trajectories/vcug-demo.jsonl).
DOME_POSE = pose_from_angles([-190.0, 30.0, 330.0])


@pytest.fixture(scope="module")
def demo():
    cfg = load_appliance(REPO / "configs" / "appliance-demo.yaml")
    return cfg, rendered_fluoroscope(cfg)


def _edge_image(shape, origin, along, at_px, lung=0.8, liver=0.3):
    """Lung above the dome (bright), liver below it, a soft edge `at_px` along `along` from `origin`."""
    rows, cols = shape
    v, u = np.mgrid[0:rows, 0:cols].astype(np.float64)
    s = (u - origin[0]) * along[0] + (v - origin[1]) * along[1]
    return (liver + (lung - liver) / (1.0 + np.exp((s - at_px) / 1.5))).astype(np.float32)


def _apex_px(cfg, fl, zoom, descent):
    """The apex and the moved apex on the 512 matrix, projected here with plain OpenCV."""
    import cv2

    T = fl.T_xray_from_webcam() @ DOME_POSE @ matrix(cfg.case.T_phantom_from_ct)
    apex = np.array(builtin_apex(cfg.case), dtype=float)
    pts = np.vstack([apex, apex - [0, 0, descent]]) @ T[:3, :3].T + T[:3, 3]
    fovs = [z.fov_mm for z in fl.zoom_levels]
    K = fl.intrinsics.K().copy()
    K[0, 0] *= fovs[0] / fovs[zoom - 1]
    K[1, 1] *= fovs[0] / fovs[zoom - 1]
    uv, _ = cv2.projectPoints(pts.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K,
                              np.asarray(fl.intrinsics.distortion.coefficients(), dtype=float))
    return uv.reshape(-1, 2), pts[0, 2]


@pytest.mark.parametrize("drawn_px", [14.0, 23.5])
def test_the_dome_shift_is_read_from_the_images_and_predicted_by_the_pinhole(demo, drawn_px):
    cfg, fl = demo
    zoom = 1
    descent = cfg.case.respiration.diaphragm_mm * (0.999 - 0.001)
    (a, m), z_apex = _apex_px(cfg, fl, zoom, descent)
    along = (m - a) / np.linalg.norm(m - a)
    shape = (fl.detector.rows, fl.detector.columns)
    e = KeptFrame(_edge_image(shape, a, along, 0.0), DOME_POSE, 0.001, zoom)
    i = KeptFrame(_edge_image(shape, a, along, drawn_px), DOME_POSE, 0.999, zoom)
    check = dome_shift(cfg, fl, e, i, builtin_apex(cfg.case))
    assert check is not None
    assert check.measured_px == pytest.approx(drawn_px, abs=0.2)
    assert check.descent_mm == pytest.approx(12.0 * 0.998)
    pitch = fl.detector.pixel_pitch_mm                                    # zoom 1, the 512 matrix
    assert check.magnification == pytest.approx(fl.geometry.source_to_image_mm / z_apex)
    closed_form_px = descent * fl.geometry.source_to_image_mm / z_apex / pitch
    assert check.predicted_px == pytest.approx(np.linalg.norm(m - a), rel=1e-6)
    assert check.predicted_px == pytest.approx(closed_form_px, rel=0.03)
    assert check.measured_mm == pytest.approx(check.measured_px * pitch, rel=1e-9)


def test_no_pair_line_without_both_images(demo):
    cfg, fl = demo
    e = KeptFrame(np.zeros((8, 8), np.float32), DOME_POSE, 0.0, 1)
    assert pair_lines(cfg, fl, {"end-expiration": e}) == []


def test_the_built_in_childs_dome_moves_diaphragm_mm_times_the_magnification(demo):
    """The whole chain short of the display: the built-in child's end-expiration CT moved by the
    breathing model to end-expiration and end-inspiration, cast by the OpenCL renderer (line
    integrals, no noise) at the demo path's dome pose; the dome's edge read from the two images
    moves diaphragm_mm x SID / SOD of the apex, within 2 %."""
    from appliance.patient import builtin
    from appliance.patient.breathing_motion import BreathingAnatomy
    from appliance.patient.breathing_timeline import BreathingTimeline
    from appliance.patient.volume import Volume
    from appliance.xray.renderer import Renderer, View

    cfg, fl = demo
    builder = builtin.Builder()
    spec = builtin.timeline()[0]
    assert (spec.stage, spec.breath) == (0, 0.0)                     # end-expiration
    ct = Volume(builder.phase(spec), builder.grid.T_ct_from_voxel)
    params = cfg.case.respiration
    anatomy = BreathingAnatomy(ct, params, cfg.case.materials)
    states = BreathingTimeline.__new__(BreathingTimeline)           # only its state_of: no device, no thread
    states.params = params
    small = fl                      # the demo's 512 matrix: the check's pixel widths are set for it
    renderer = Renderer(small, cfg.case.materials, contrast=cfg.case.contrast, device="cpu")
    T = small.T_xray_from_webcam() @ DOME_POSE @ matrix(cfg.case.T_phantom_from_ct)
    images = [renderer.render(renderer.prepare(anatomy.volume_at(states.state_of(e))), T,
                              View(quantity="line-integral", noise=False)).image for e in (0.0, 1.0)]
    check = dome_shift(cfg, small, KeptFrame(images[0], DOME_POSE, 0.0, 1), KeptFrame(images[1], DOME_POSE, 1.0, 1),
                       builtin_apex(cfg.case))
    assert check is not None and check.descent_mm == pytest.approx(params.diaphragm_mm)
    assert check.predicted_mm == pytest.approx(params.diaphragm_mm * check.magnification, rel=0.03)
    assert check.measured_px == pytest.approx(check.predicted_px, rel=0.02)
