"""The bench's finer grids of the adult chest are the same patient wherever they are cut: two
boxes of it drawn on their own grids, offset by whole voxels, hold the same HU voxel for voxel
where they overlap (the same vessels, ribs and gas), placed where the voxel grid says."""

from __future__ import annotations

import numpy as np

from appliance.xray.anatomy_reference import adult_chest_box

SPACING = (4.0, 3.2, 3.2)       # z, y, x mm: coarse, to keep it quick; any grid draws the same patient


def test_two_boxes_of_the_adult_chest_agree_where_they_overlap():
    # Across the right lung (x < 0 is the patient's right), from the front wall to the back.
    lo_a, hi_a = np.array([-110.0, -100.0, 20.0]), np.array([-30.0, 100.0, 80.0])
    shift = np.array([5, 7, 3])                         # voxels (x, y, z) box b starts further on
    sx, sy, sz = SPACING[2], SPACING[1], SPACING[0]
    lo_b = lo_a + shift * (sx, sy, sz)
    a = adult_chest_box(lo_a, hi_a, SPACING, ct_noise=False)
    b = adult_chest_box(lo_b, hi_a + 20.0, SPACING, ct_noise=False)
    np.testing.assert_allclose(a.T_ct_from_voxel[:3, 3], lo_a)
    np.testing.assert_allclose(np.diag(a.T_ct_from_voxel)[:3], (sx, sy, sz))
    assert a.hu.shape == (16, 64, 26)                   # (80 / 3.2 + 1, 200 / 3.2 + 1 rounded up, 60 / 4 + 1) voxels
    overlap = a.hu[shift[2]:, shift[1]:, shift[0]:]
    np.testing.assert_array_equal(b.hu[:overlap.shape[0], :overlap.shape[1], :overlap.shape[2]], overlap)
    # The lung is there: most of the box's middle is aerated lung (about -850 HU), with vessels in it.
    middle = a.hu[4:12, 20:44, 5:20]
    assert np.mean(middle < -600) > 0.5 and (middle > -300).any()
