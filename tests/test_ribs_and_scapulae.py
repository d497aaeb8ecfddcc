"""Ribs from HU alone on a CT whose scapulae touch the upper ribs: the ribs turn, the scapulae stay.

Ground truth: synthetic_rib_cage draws each rib's axis and each scapula's extent in closed form;
the rigid law is the seed's two rotations about the costovertebral joint (scipy's rotations
here, not the code's matrices). Both ways of telling ribs from scapulae are tested: the default
(bone standing taller than a rib is a plate) and that with the lung-lining rule added.
"""

import numpy as np
import pytest
import synthetic_chest as sc
import synthetic_rib_cage as rc
from scipy import ndimage
from scipy.spatial.transform import Rotation

from appliance.config.case import Materials, Respiration
from appliance.patient.breathing_motion import BreathingAnatomy


@pytest.fixture(scope="module")
def cage():
    return rc.rib_cage()


#: The default, and the default with the lung-lining rule (rib bone lines the lungs within 10 mm).
PARAMS = Respiration()
RULES = {"plates": PARAMS, "plates+lining": Respiration(rib_pleura_max_mm=10.0)}


@pytest.fixture(scope="module", params=sorted(RULES))
def anatomy(cage, request):
    return BreathingAnatomy(cage[0], RULES[request.param], Materials())


def _rib_cover(anatomy) -> np.ndarray:
    """Which voxels of the CT some rib's rigid body holds."""
    held = np.zeros(anatomy.shape, bool)
    for rib in anatomy.ribs:
        held[rib.box] |= rib.alpha > 0
    return held


def test_on_the_ct_the_scapula_and_the_upper_ribs_are_one_piece_of_bone(cage):
    """The case being tested: a threshold and connected components alone (rib_max_height_mm
    null, no rib_pleura_max_mm) move the scapula with both upper ribs of its side, as one rigid body."""
    ct, parts = cage
    plain = BreathingAnatomy(ct, Respiration(rib_max_height_mm=None), Materials())
    held = _rib_cover(plain)
    assert held[parts["scapulae"]].mean() > 0.9 and len(plain.ribs) == 2 + 2
    pieces, _ = ndimage.label((ct.hu >= Materials().bone_min_hu) & ~parts["spine"])
    _, x, _, z = sc.grid()
    for side in (-1, 1):
        scapula = np.unique(pieces[parts["scapulae"] & (np.sign(x) == side)])
        assert len(scapula) == 1
        for zr in rc.RIB_Z[:2]:
            assert scapula[0] in pieces[parts["ribs"] & (np.sign(x) == side) & (np.abs(z - zr) < 3)]


def test_every_rib_is_its_own_rigid_body_and_no_scapula_voxel_is_in_one(cage, anatomy):
    _, parts = cage
    _, x, _, z = sc.grid()
    assert len(anatomy.ribs) == 2 * len(rc.RIB_Z)
    found = sorted((rib.side, round(rib.head_ct[2] / 10.0)) for rib in anatomy.ribs)
    # One rib per side and height (each joint within a voxel of its rib's height).
    assert found == sorted((s, round(zr / 10.0)) for zr in rc.RIB_Z for s in (-1, 1))
    held = _rib_cover(anatomy)
    assert not (held & parts["scapulae"]).any()
    # Each rib's own tube, beyond the spine's band, is held (the necks between the spine and the lung too).
    outside_spine = np.abs(x) > PARAMS.spine_half_width_mm + sc.SPACING
    assert held[parts["ribs"] & outside_spine].mean() > 0.98


def test_a_scapula_voxel_stays_while_the_ribs_under_it_turn(cage, anatomy):
    ct, parts = cage
    moved = anatomy.hu_at(2.0, 3.0, 12.0)
    # Away from where the turned ribs can reach (their ends move a few mm).
    clear = ndimage.distance_transform_edt(~parts["ribs"], sampling=sc.SPACING) > 8.0
    scapula = parts["scapulae"] & clear
    assert scapula.sum() > 500
    assert np.array_equal(moved[scapula], ct.hu[scapula].astype(np.float32))
    ribs = parts["ribs"] & clear.__invert__()
    assert not np.array_equal(moved[ribs], ct.hu[ribs].astype(np.float32))


@pytest.mark.parametrize("zr", rc.RIB_Z)
def test_a_rib_touching_the_scapula_turns_as_the_rigid_law_predicts(cage, anatomy, zr):
    """The rib's lateral point (on its axis, far from the scapula) moves to J + R (P - J): the
    bone's centroid within 7 mm of that point in the moved CT is the point, within 0.3 voxel."""
    gamma, lam, side = 2.0, 3.0, -1
    rib = next(r for r in anatomy.ribs if r.side == side and abs(r.head_ct[2] - zr) < 5.0)
    P = rc.rib_axis(zr, side, 0.0)[0]
    R = (Rotation.from_rotvec(np.radians(gamma) * np.array([0.0, -side, 0.0]))
         * Rotation.from_rotvec(np.radians(lam) * np.array([-1.0, 0.0, 0.0])))
    expect = rib.head_ct + R.apply(P - rib.head_ct)
    _, x, y, z = sc.grid()
    pts = np.stack([x, y, z], axis=-1)

    def centroid(hu, at):
        w = np.clip((hu - 40.0) / (rc.HU_RIB - 40.0), 0.0, 1.0) * (np.linalg.norm(pts - at, axis=-1) <= 7.0)
        return (pts * w[..., None]).sum(axis=(0, 1, 2)) / w.sum()

    # The lateral point moves across the tube's axis by far more than a voxel; the tube's centroid
    # in a ball is on its axis only where the axis runs straight through, hence along z and y.
    assert np.linalg.norm(expect - P) > 3.0
    rest = centroid(anatomy.hu_at(0.0, 0.0, 0.0), P)
    got = centroid(anatomy.hu_at(gamma, lam, 0.0), expect)
    assert np.linalg.norm((rest - P)[1:]) < 0.3 * sc.SPACING
    assert np.linalg.norm((got - expect)[1:]) < 0.3 * sc.SPACING, (got, expect)
