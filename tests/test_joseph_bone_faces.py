"""Joseph's samples across a bone face, against the closed-form chords of a thin dense plate.

The plate is the bar pattern's in miniature: 1 mm of 3000 HU on two 0.5 mm slices, its voxels
0.02 mm along x. The rays cross it 0.045 to 0.06 rad off its normal, where 0.02 / 0.5 = 0.04 makes
x Joseph's dominant axis in index units, so every sample interpolates across the plate's faces in
z: half in the plate and half in air. Bone density is linear in HU from the soft-tissue value at
bone_min_hu (case.Materials), so the plate's bone integral is its chord times that density at
3000 HU, whatever each sample's share of it; a sample whose interpolated HU were read as bone
(offset + slope x HU) would count half the plate as 0.8 of its density.
"""

from __future__ import annotations

import numpy as np
import pytest

from appliance.config.case import Materials
from appliance.geometry import make_transform
from appliance.xray.bench import flat_profile
from appliance.xray.renderer import Renderer, View, zoomed_K
from appliance.xray.truth.analytic import box_chords, box_volume, pixel_rays_ct

SIZE, ZOOM, DEPTH_MM = 128, 4, 1000.0
#: 1000 voxels of 0.02 mm along x (20 mm), 8 of 1 mm along y, 6 slices of 0.5 mm; the plate
#: fills slices 2..3 over the whole x and y range but a voxel at each end.
SHAPE_ZYX, SPACING_XYZ = (6, 8, 1000), (0.02, 1.0, 0.5)
LO, HI = (1, 1, 2), (998, 6, 3)
BAR_HU = 3000
#: The plate's x centre (mm): 45 to 60 mm off the axis at 1000 mm, 0.045 to 0.06 rad.
PLATE_X_MM = 52.5


def _bone_density(m: Materials, hu: float) -> float:
    """g/cm^3: the field docs' line from (bone_min_hu, 1 + bone_min_hu / 1000) to (1000, density at 1000 HU)."""
    at_min = 1.0 + m.bone_min_hu / 1000.0
    return at_min + (hu - m.bone_min_hu) * (m.bone_density_at_1000_hu_g_per_cm3 - at_min) / (1000.0 - m.bone_min_hu)


@pytest.fixture(scope="module")
def plate():
    vol, lo, hi = box_volume(SHAPE_ZYX, SPACING_XYZ, LO, HI, hu=BAR_HU)
    T = make_transform(np.eye(3), [-PLATE_X_MM, 0.0, DEPTH_MM])     # the plate's centre 52.5 mm off the axis
    s, d = pixel_rays_ct(zoomed_K(flat_profile(SIZE), ZOOM), T, SIZE, SIZE)
    return vol, T, d, box_chords(s, d, lo, hi)


#: The profiles' block sampling weighs each step's share of the plate over the ray's own travel in
#: z (0.8 slice per step), exact for a step function; linear interpolation ramps each face over a
#: whole slice, and samples 0.8 slice apart sum that ramp to within 4 % (a 3.7 % worst case here).
@pytest.mark.parametrize("edge_px, rtol", [(4.0, 0.005), (None, 0.04)])
@pytest.mark.parametrize("packet", [True, False])
def test_a_thin_plate_crossed_along_its_fine_axis_reads_its_chord(plate, edge_px, rtol, packet):
    vol, T, dirs, chords = plate
    fl = flat_profile(SIZE)
    fl = fl.model_copy(update={"ct_sampling": fl.ct_sampling.model_copy(update={"voxel_edge_px": edge_px})})
    renderer = Renderer(fl, Materials(), device="cpu", packet=packet)
    lines = renderer.material_integrals(renderer.prepare(vol), T, View(zoom=ZOOM), distorted=False, circle=False)
    # Rays through the whole thickness, a voxel or more from the plate's x and y ends.
    through = chords > 0.999
    assert through.sum() > 60
    bone = lines[..., 2][through] / _bone_density(Materials(), BAR_HU)
    # Every one steps along x in index units (|dx| / 0.02 mm > |dz| / 0.5 mm): the case in question.
    slope = np.abs(dirs[..., 0] / dirs[..., 2])[through]
    assert slope.min() > SPACING_XYZ[0] / SPACING_XYZ[2]
    np.testing.assert_allclose(bone, chords[through], rtol=rtol)
    # Nothing of the plate leaks into the other materials.
    assert np.abs(lines[..., :2][through]).max() < 0.01 * chords.max()
