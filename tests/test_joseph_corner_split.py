"""Joseph's samples split their corners at bone_min: each material of a mixed sample against closed form.

The geometry is test_joseph_bone_faces': a 1 mm plate on two 0.5 mm slices, voxels 0.02 mm along
x, crossed 0.045 to 0.06 rad off its normal, so every sample of Joseph's (x its dominant axis in
index units) mixes the plate's corners with their neighbours across its faces in z. With block
sampling (4 px) each sample weighs its step's share of a face exactly, so each material's integral
is its chord times its density to 0.5 %. Here the plate's neighbours and the plate itself take the
values where the split's rules decide: HU exactly at bone_min (bone), lung above air's density
(air, whatever bone shares the sample), iodine above contrast_min (contrast by its weight only),
and two phases blended at their ends (the blend's corners are each phase's own), in both kernels:
the CPU's 16-ray packets and the one ray per work-item that GPUs run.
"""

from __future__ import annotations

import numpy as np
import pytest

from appliance.config.case import Materials
from appliance.geometry import make_transform
from appliance.xray.bench import flat_profile
from appliance.xray.projection_cache import ProjectionCache
from appliance.xray.renderer import Renderer, View, zoomed_K
from appliance.xray.truth.analytic import box_chords, box_volume, pixel_rays_ct

SIZE, ZOOM, DEPTH_MM = 128, 4, 1000.0
SHAPE_ZYX, SPACING_XYZ = (8, 8, 1000), (0.02, 1.0, 0.5)
#: The plate on slices 3..4; the lung around it on slices 2..5 (index ranges inclusive, i j k).
PLATE_LO, PLATE_HI = (1, 1, 3), (998, 6, 4)
LUNG_LO, LUNG_HI = (1, 1, 2), (998, 6, 5)
PLATE_X_MM = 52.5
#: Lung: 0.1 g/cm^3 by the field docs' 1 + HU / 1000, and at or below air_max_hu (-800): air.
LUNG_HU = -900
#: Block sampling's exactness for a step across a face (test_joseph_bone_faces: 0.5 %).
RTOL = 0.005


def _bone_density(m: Materials, hu: float) -> float:
    """g/cm^3: the field docs' line from (bone_min_hu, 1 + bone_min_hu / 1000) to (1000, density at 1000 HU)."""
    at_min = 1.0 + m.bone_min_hu / 1000.0
    return at_min + (hu - m.bone_min_hu) * (m.bone_density_at_1000_hu_g_per_cm3 - at_min) / (1000.0 - m.bone_min_hu)


def _renderer(materials: Materials, packet: bool) -> Renderer:
    fl = flat_profile(SIZE)
    fl = fl.model_copy(update={"ct_sampling": fl.ct_sampling.model_copy(update={"voxel_edge_px": 4.0})})
    return Renderer(fl, materials, device="cpu", packet=packet)


POSE = make_transform(np.eye(3), [-PLATE_X_MM, 0.0, DEPTH_MM])


@pytest.fixture(scope="module")
def rays():
    s, d = pixel_rays_ct(zoomed_K(flat_profile(SIZE), ZOOM), POSE, SIZE, SIZE)
    return s, d


def _plate(hu: int, lung: bool = False, lo=PLATE_LO, hi=PLATE_HI):
    """The plate of `hu` in air, or in lung; returns the Volume and the plate's corners (mm)."""
    vol, lo_mm, hi_mm = box_volume(SHAPE_ZYX, SPACING_XYZ, lo, hi, hu=hu)
    if lung:
        (i0, j0, k0), (i1, j1, k1) = LUNG_LO, LUNG_HI
        arr = vol.hu.copy()
        arr[k0:k1 + 1, j0:j1 + 1, i0:i1 + 1] = np.where(arr[k0:k1 + 1, j0:j1 + 1, i0:i1 + 1] == hu, hu, LUNG_HU)
        # Air is left out of the content box and outline the rays are clipped to; in a patient
        # the lung lies within soft tissue. Soft voxels at the grid's eight corners hold both open
        # (over a box, every plane's n.p is extreme at a corner).
        arr[::arr.shape[0] - 1, ::arr.shape[1] - 1, ::arr.shape[2] - 1] = 0
        vol = type(vol)(hu=arr, T_ct_from_voxel=vol.T_ct_from_voxel, source="plate in lung")
    return vol, lo_mm, hi_mm


def _lines(renderer: Renderer, vol, blend=None) -> np.ndarray:
    b = None if blend is None else (renderer.prepare(blend[0]), blend[1])
    return renderer.material_integrals(renderer.prepare(vol), POSE, View(zoom=ZOOM), blend=b, distorted=False,
                                       circle=False)


def _through(chords: np.ndarray) -> np.ndarray:
    """Rays through the plate's whole thickness, away from its ends (its chord is 1 mm / cos)."""
    through = chords > 0.999
    assert through.sum() > 60
    return through


#: A plate at exactly a class's bound: at or below air_max_hu (-800) air, at or above bone_min_hu
#: (300) bone, either way of soft tissue's density there, 1 + HU / 1000 (0.2 and 1.3 g/cm^3); at
#: or above contrast_min_hu contrast (its column is the iodinated water's volume, 1 g/cm^3).
#: 2048 HU, a power of two, scales each sample's weights exactly, so a face's mixed samples meet
#: the bound exactly too.
BOUNDS = [("air_max_hu", Materials(), 0, 0.2), ("bone_min_hu", Materials(), 2, 1.3),
          ("contrast_min_hu", Materials(contrast_min_hu=2048.0), 3, 1.0)]


@pytest.mark.parametrize("bound, m, column, density", BOUNDS, ids=[b[0] for b in BOUNDS])
@pytest.mark.parametrize("packet", [True, False])
def test_a_plate_at_exactly_a_class_bound_reads_as_that_class(rays, bound, m, column, density, packet):
    vol, lo, hi = _plate(int(getattr(m, bound)))
    chords = box_chords(*rays, lo, hi)
    through = _through(chords)
    lines = _lines(_renderer(m, packet), vol)[through]
    np.testing.assert_allclose(lines[:, column] / density, chords[through], rtol=RTOL)
    others = [c for c in range(4) if c != column]
    assert np.abs(lines[:, others]).max() < 1e-3


@pytest.mark.parametrize("packet", [True, False])
def test_lung_sharing_samples_with_bone_stays_air_of_its_own_density(rays, packet):
    m = Materials()
    vol, lo, hi = _plate(3000, lung=True)
    s, d = rays
    plate = box_chords(s, d, lo, hi)
    _, lung_lo, lung_hi = box_volume(SHAPE_ZYX, SPACING_XYZ, LUNG_LO, LUNG_HI)
    lung = box_chords(s, d, lung_lo, lung_hi) - plate
    # Rays a voxel or more from the soft corners (which samples interpolate a voxel beyond).
    near = [box_volume(SHAPE_ZYX, SPACING_XYZ, (i, j, 0), (i + 1, j + 1, 7))[1:] for i in (0, 998) for j in (0, 6)]
    far = np.all([box_chords(s, d, *c) == 0 for c in near], axis=0)
    through = _through(plate) & (lung > 0.999) & far
    lines = _lines(_renderer(m, packet), vol)[through]
    np.testing.assert_allclose(lines[:, 2] / _bone_density(m, 3000), plate[through], rtol=RTOL)
    # The lung's corners in a sample with the plate's are read by their own mean HU, -900: air of
    # 0.1 g/cm^3 (their share of the sample), never soft tissue.
    np.testing.assert_allclose(lines[:, 0] / 0.1, lung[through], rtol=2 * RTOL)
    assert np.abs(lines[:, [1, 3]]).max() < 1e-4


@pytest.mark.parametrize("packet", [True, False])
def test_iodine_above_contrast_min_reads_as_contrast_by_its_share_of_each_sample(rays, packet):
    m = Materials(contrast_min_hu=2000.0)
    vol, lo, hi = _plate(3000)
    chords = box_chords(*rays, lo, hi)
    through = _through(chords)
    lines = _lines(_renderer(m, packet), vol)
    # The contrast column is the iodinated water's volume (g/cm^3 of water, 1): the chord in mm.
    np.testing.assert_allclose(lines[..., 3][through], chords[through], rtol=RTOL)
    assert np.abs(lines[..., :3][through]).max() < 1e-3


@pytest.fixture(scope="module")
def two_phases():
    """Phase a the plate, phase b the plate a slice deeper (slices 4..5): their z faces differ."""
    a, lo_a, hi_a = _plate(3000)
    b, lo_b, hi_b = _plate(3000, lo=(1, 1, 4), hi=(998, 6, 5))
    return a, b, lo_a, hi_a, lo_b, hi_b


@pytest.mark.parametrize("packet", [True, False])
def test_two_phases_blended_at_their_ends_read_each_phases_chords(rays, two_phases, packet):
    a, b, lo_a, hi_a, lo_b, hi_b = two_phases
    m = Materials()
    r = _renderer(m, packet)
    rho = _bone_density(m, 3000)
    for w, lo, hi in ((0.0, lo_a, hi_a), (1.0, lo_b, hi_b)):
        chords = box_chords(*rays, lo, hi)
        through = _through(chords)
        bone = _lines(r, a, blend=(b, w))[..., 2]
        np.testing.assert_allclose(bone[through] / rho, chords[through], rtol=RTOL, err_msg=f"blend weight {w}")


def test_both_phases_cast_in_one_pass_read_each_phases_chords(rays, two_phases):
    """The packet kernel's SPLIT pass (two phases on one grid, cached in projection space): the
    midway frame is the mean of the two phases' own bone integrals, each against its chords."""
    a, b, lo_a, hi_a, lo_b, hi_b = two_phases
    m = Materials()
    r = _renderer(m, True)
    cache = ProjectionCache(r)
    pa, pb = r.prepare(a), r.prepare(b)
    mid = cache.material_integrals(pa, POSE, View(zoom=ZOOM), blend=(pb, 0.5))[..., 2]
    assert cache.counts.paired == 1
    ca, cb = box_chords(*rays, lo_a, hi_a), box_chords(*rays, lo_b, hi_b)
    through = _through(ca) & _through(cb)
    # The flat detector has no distortion, and its field's edge lies outside these rays.
    rho = _bone_density(m, 3000)
    np.testing.assert_allclose(mid[through] / rho, 0.5 * (ca + cb)[through], rtol=RTOL)


#: Materials under which the halo (-950 HU) is air, bone or contrast, and the plate's material
#: column (0-3: air, soft tissue, bone, contrast): with bone_min at -960 HU the 3000 HU plate is
#: bone, or contrast above contrast_min.
HALO_HU = -950
HALO_CASES = [
    (Materials(), 2),
    (Materials(air_max_hu=-990.0, bone_min_hu=-960.0, contrast_min_hu=0.0), 3),
    (Materials(air_max_hu=-990.0, bone_min_hu=-960.0, contrast_min_hu=-955.0), 3),
]


@pytest.mark.parametrize("materials, plate_column", HALO_CASES, ids=["air", "bone", "contrast"])
@pytest.mark.parametrize("packet", [True, False])
def test_voxels_outside_the_content_box_add_nothing_whatever_their_material(rays, materials, plate_column, packet):
    """Voxels at or below -900 HU lie outside the content box the rays are clipped to (the prepared
    volume's contract): the grid's outer slices, three beyond the plate's, at -950 HU, add nothing to
    any ray. A packet's rays step through the union of their slice ranges, each ray's samples beyond
    its own range reaching those slices; they must add nothing, whichever material -950 HU is."""
    vol, lo, hi = _plate(3000)
    arr = vol.hu.copy()
    arr[[0, -1]] = HALO_HU
    vol = type(vol)(hu=arr, T_ct_from_voxel=vol.T_ct_from_voxel, source="plate in a halo")
    chords = box_chords(*rays, lo, hi)
    through = _through(chords)
    lines = _lines(_renderer(materials, packet), vol)[through]
    density = _bone_density(materials, 3000) if plate_column == 2 else 1.0
    np.testing.assert_allclose(lines[:, plate_column] / density, chords[through], rtol=RTOL)
    others = [c for c in range(4) if c != plate_column]
    assert np.abs(lines[:, others]).max() < 1e-4
