"""The breathing anatomy on a CT that is not the built-in patient: rigid ribs, the dome in the image."""


import numpy as np
import pytest
import synthetic_chest as sc
from scipy.spatial.transform import Rotation

from appliance.config.case import Materials, Respiration
from appliance.geometry import make_transform
from appliance.patient.breathing_motion import BreathingAnatomy
from appliance.patient.respiration import BreathingControl, state_at
from appliance.xray.bench import flat_profile
from appliance.xray.renderer import Renderer, View

SOD = 750.0
#: AP view: the beam runs anterior to posterior (+y), the patient's head at the top of the image.
T_XRAY_FROM_CT = make_transform(np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]]), [0.0, 0.0, SOD])


@pytest.fixture(scope="module")
def ct():
    return sc.chest()


@pytest.fixture(scope="module")
def anatomy(ct):
    return BreathingAnatomy(ct, Respiration(), Materials())


@pytest.fixture(scope="module")
def renderer():
    return Renderer(flat_profile(128), Materials(), device="cpu")


def test_ribs_found_from_thresholds_with_joints_beside_the_spine(anatomy):
    assert len(anatomy.ribs) == len(sc.RIBS)
    for rib in anatomy.ribs:
        # The joint is where the rod leaves the spine's band (|x| = 28 mm), on the rod's axis.
        zr, s = min(sc.RIBS, key=lambda r: abs(r[0] - rib.head_ct[2] - 4) + 100 * (r[1] != rib.side))
        p, q = sc.rib_ends(zr, s)
        t = (abs(rib.head_ct[0]) - 14.0) / 81.0
        on_axis = p + t * (q - p)
        assert rib.side == s
        assert np.linalg.norm(rib.head_ct - on_axis) <= sc.RIB_RADIUS + sc.SPACING
        assert 27.0 <= abs(rib.head_ct[0]) <= 33.0


@pytest.fixture(scope="module")
def labelled():
    """The chest with its lungs labelled rather than aired (soft tissue all round the ribs, so a
    rib's voxels above a threshold are the rib, unbiased by what lies beside it)."""
    params = Respiration(label_map="labels.nii.gz", labels={"lungs": list(sc.LUNG_LABELS), "spine": [sc.SPINE_LABEL]})
    return BreathingAnatomy(sc.chest(lung_hu=40.0), params, Materials(), sc.chest_labels())


def test_labels_give_the_spine_and_the_joints_at_its_side(labelled):
    assert len(labelled.ribs) == len(sc.RIBS)
    for rib in labelled.ribs:
        assert 10.0 <= abs(rib.head_ct[0]) <= 17.5 and 30.0 <= rib.head_ct[1] <= 45.0


@pytest.mark.parametrize("gamma, lam", [(2.0, 3.0), (6.0, 0.0), (0.0, 8.0)])
def test_a_rib_moves_as_the_rigid_rotation_predicts(labelled, gamma, lam):
    anatomy = labelled
    moved = anatomy.hu_at(gamma, lam, 0.0)
    rest_hu = anatomy.hu_at(0.0, 0.0, 0.0)
    _, x, y, z = sc.grid()
    for rib in anatomy.ribs:
        # This rib's neighbourhood: its side, outside the spine, within 15 mm of its head's height.
        near = (np.sign(x) == rib.side) & (np.abs(x) > 12.0) & (np.abs(z - rib.head_ct[2] + 8.0) < 17.0)
        pts = np.stack([x, y, z], axis=-1)

        def centroid(hu, near=near, pts=pts):
            # Bone coverage of each voxel: 0 in soft tissue (40 HU), 1 inside a rod (900 HU).
            w = np.clip((hu - 40.0) / 860.0, 0.0, 1.0) * near
            return (pts * w[..., None]).sum(axis=(0, 1, 2)) / w.sum()
        rest, got = centroid(rest_hu), centroid(moved)
        R = (Rotation.from_rotvec(np.radians(gamma) * np.array([0.0, -rib.side, 0.0]))
             * Rotation.from_rotvec(np.radians(lam) * np.array([-1.0, 0.0, 0.0])))
        expect = rib.head_ct + R.apply(rest - rib.head_ct)
        assert np.linalg.norm(got - expect) < 0.3 * sc.SPACING, (rib.side, rib.head_ct, got, expect)
        assert np.linalg.norm(expect - rest) > 2.0           # it did move
        # The lateral end rises with gamma, the front with lambda: the seed's two rotations.
        assert got[2] > rest[2]


def test_spine_stays_still_and_soft_tissue_follows_the_tendon(anatomy, ct):
    moved = anatomy.hu_at(2.0, 3.0, 15.0)
    spine = ct.hu >= 650
    spine_band = spine & (np.abs(sc.grid()[1]) < 12)
    assert np.array_equal(moved[spine_band], ct.hu[spine_band].astype(np.float32))
    # The soft-tissue field: the full descent at the dome, nothing at the lung apex.
    d = anatomy.displacement_mm([[-50, 0, 10.0], [-50, 0, 138.0], [-50, 0, -200.0]], 15.0)
    assert d[0, 2] == pytest.approx(-15.0) and d[1, 2] == pytest.approx(0.0, abs=0.5) and d[2, 2] == 0.0


def dome_edge_row(image, column, level, start):
    """Sub-pixel row, from `start` down, where the line integral of `column` climbs through
    `level`: from the lung into the liver (`start` below the ribs' shadows)."""
    prof = image[:, column].astype(float)
    rows = np.flatnonzero((prof[:-1] < level) & (prof[1:] >= level))
    r = rows[rows >= start][0]
    return r + (level - prof[r]) / (prof[r + 1] - prof[r])


def test_dome_in_the_rendered_image_follows_the_amplitude(anatomy, renderer):
    """Half the amplitude, half the dome's excursion (within 10 %); the full excursion is the
    pinhole projection of the set amplitude at the dome's depth."""
    f = renderer.fluoroscope
    column = int(round(f.intrinsics.cx + f.intrinsics.fx * -50.0 / SOD))      # through the right dome's apex
    rows, level = {}, None
    for amp in (0.0, 7.5, 15.0):
        # End-inspiration (t = 1/(4f)) of a case with that amplitude.
        params = Respiration(diaphragm_mm=amp, rib_gamma_deg=0, rib_lambda_deg=0)
        s = state_at(params, 1.0)
        prepared = renderer.prepare(anatomy.volume_at(s))
        image = renderer.line_integral(prepared, T_XRAY_FROM_CT)
        if level is None:      # half way between the lung above the dome and the liver below it, at rest
            prof = image[:, column]
            r_apex = int(round(f.intrinsics.cy - f.intrinsics.fy * sc.DOME_APEX_Z / SOD))
            level = 0.5 * (prof[r_apex - 8] + prof[r_apex + 8])
        rows[amp] = dome_edge_row(image, column, level, r_apex - 6)
    full, half = rows[15.0] - rows[0.0], rows[7.5] - rows[0.0]
    # The dome at depth SOD (the ct origin; the apex at y = 0): 15 mm -> fy * 15 / SOD pixels, downward.
    expect = f.intrinsics.fy * 15.0 / SOD
    assert full == pytest.approx(expect, rel=0.1)
    assert half / full == pytest.approx(0.5, rel=0.1)


def test_hold_freezes_the_image(anatomy, renderer):
    """Held: two frames differ only by quantum noise; breathing on, the difference is far larger."""
    params = Respiration()
    c = BreathingControl(params)
    view = View(quantity="intensity", noise=True)
    c.hold(0.5)
    frames = [renderer.render(renderer.prepare(anatomy.volume_at(c.at(t))), T_XRAY_FROM_CT, view).image for t in (0.5, 2.5)]
    c.resume(2.5)
    moving = renderer.render(renderer.prepare(anatomy.volume_at(c.at(4.5))), T_XRAY_FROM_CT, view).image
    held_diff = np.abs(frames[0] - frames[1])
    # Poisson noise of two independent frames: the difference's sd is sqrt(2 I / N) relative.
    photons = renderer.photons_per_pixel(1)
    sel = frames[0] > 0.05
    expect_sd = np.sqrt(2 * frames[0][sel] / photons)
    assert np.sqrt(np.mean((held_diff[sel] / expect_sd) ** 2)) == pytest.approx(1.0, rel=0.15)
    assert np.abs(moving - frames[1])[sel].mean() > 1.5 * held_diff[sel].mean()
