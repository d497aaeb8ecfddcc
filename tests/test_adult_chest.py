"""The synthetic adult chest CT against adult anatomy known independently of the generator.

Ground truth: tissue Hounsfield units (air -1000, aerated lung -800 to -900, fat -100,
soft tissue 30-60, liver 50-70, cortical bone above 700), an adult chest about 330 mm wide
and 220 mm deep, twelve ribs down each side, the right dome of the diaphragm above the left,
and DICOM's LPS frame (+x the patient's left, +z superior) surviving a round trip through a file.
"""

from __future__ import annotations

import numpy as np
import pytest

from appliance.config.case import CaseProfile
from appliance.config.loading import load_profile
from appliance.errors import FluorosimError
from appliance.patient.adult_body import LEFT_DOME, RIGHT_DOME
from appliance.patient.adult_chest import SIZES, build_adult_chest
from appliance.patient.volume_io import load_volume


@pytest.fixture(scope="module")
def chest():
    shape, spacing = SIZES["small"]
    return build_adult_chest(shape, spacing, seed=3)


def index(origin, spacing, point):
    """[k, j, i] of the voxel nearest an LPS point (mm)."""
    sz, sy, sx = spacing
    return tuple(int(round((p - o) / s)) for p, o, s in zip(point[::-1], origin[::-1], (sz, sy, sx)))


def hu_at(chest, point):
    hu, spacing, origin = chest
    k, j, i = index(origin, spacing, point)
    return float(np.median(hu[k, j - 1:j + 2, i - 1:i + 2]))


def test_grid_is_centred_int16_lps(chest):
    hu, spacing, origin = chest
    assert hu.dtype == np.int16 and hu.shape == SIZES["small"][0]
    assert spacing == SIZES["small"][1]
    nz, ny, nx = hu.shape
    assert origin == pytest.approx((-(nx - 1) / 2 * 3.2, -(ny - 1) / 2 * 3.2, -(nz - 1) / 2 * 5.0))


def test_tissues_have_their_hounsfield_units(chest):
    assert hu_at(chest, (0, -190, 0)) < -980                # air in front of the chest
    assert -900 < hu_at(chest, (-100, -20, 90)) < -780     # right upper lung
    assert -900 < hu_at(chest, (100, 0, 90)) < -780        # left upper lung
    assert 40 < hu_at(chest, (-90, 0, -70)) < 80           # liver, under the right dome
    assert hu_at(chest, (0, 0, 150)) < -900                # the trachea's air column
    assert -130 < hu_at(chest, (150, 0, 0)) < 80           # chest wall, beside the lungs


def test_body_has_adult_size(chest):
    hu, spacing, origin = chest
    k = index(origin, spacing, (0, 0, 40))[0]
    body = hu[k] > -500
    cols = np.flatnonzero(body.any(axis=0))
    rows = np.flatnonzero(body.any(axis=1))
    width, depth = (cols[-1] - cols[0] + 1) * spacing[2], (rows[-1] - rows[0] + 1) * spacing[1]
    assert 300 < width < 370 and 190 < depth < 250


def test_twelve_ribs_down_each_side(chest):
    """A vertical line through the lateral chest wall crosses each rib once."""
    hu, spacing, origin = chest
    for x in (-150.0, 150.0):
        k0, j, i = index(origin, spacing, (x, 20.0, 0.0))
        column = hu[:, j - 2:j + 3, i - 3:i + 4].max(axis=(1, 2))
        bone = column > 400
        runs = np.count_nonzero(bone[1:] & ~bone[:-1]) + int(bone[0])
        assert 8 <= runs <= 12, f"x={x}: {runs} ribs crossed"


def test_spine_has_cortex_and_cancellous_bone(chest):
    hu, spacing, origin = chest
    k, j, i = index(origin, spacing, (0, 0, 0))
    column = hu[:, :, i]
    bone_rows = np.flatnonzero((column > 150).sum(axis=0) > hu.shape[0] // 2)
    assert bone_rows.size, "no vertebral column along z at the midline"
    assert column.max() > 700       # cortex


def test_right_dome_above_left(chest):
    hu, spacing, origin = chest

    def dome_top(x):
        """z (mm) where, going down a line behind the heart, soft tissue starts for good."""
        _, j, i = index(origin, spacing, (x, 50.0, 0.0))
        solid = hu[:, j, i] > -300
        for k in range(hu.shape[0] - 1, 2, -1):
            if k < hu.shape[0] - 10 and solid[k - 3:k + 1].all():
                return origin[2] + k * spacing[0]
        raise AssertionError(f"no diaphragm under x={x}")
    assert RIGHT_DOME[2] > LEFT_DOME[2]
    right, left = dome_top(-100.0), dome_top(100.0)
    assert right > left and -60 < left < 20 and -40 < right < 30


def test_lungs_hold_vessels(chest):
    """Branching vessels: soft-tissue voxels inside the lung fields, more near the hila."""
    hu, spacing, origin = chest
    k = index(origin, spacing, (0, 0, 60))[0]
    sl = hu[k]
    lung = sl < -700
    vessels = (sl > -300) & (np.roll(lung, 2, 0) | np.roll(lung, -2, 0)) & (np.roll(lung, 2, 1) | np.roll(lung, -2, 1))
    assert vessels.sum() >= 10


def test_round_trip_through_a_file_keeps_hu_and_frame(chest, tmp_path, capsys):
    from appliance.cli import main

    assert main(["case", "adult-chest", "--out", str(tmp_path), "--size", "small", "--seed", "3"]) == 0
    profile_path = tmp_path / "adult-chest.yaml"
    assert str(profile_path) in capsys.readouterr().out
    case = load_profile(profile_path, CaseProfile)
    volume = load_volume(tmp_path / case.phases[0].volume)
    hu, spacing, origin = chest
    assert np.array_equal(volume.hu, hu)
    assert np.allclose(volume.T_ct_from_voxel[:3, 3], origin)
    assert np.allclose(volume.spacing_mm, spacing[::-1])
    assert case.patient.age_years >= 18 and case.respiration is None
    # Beside it the same CT breathing as an adult at rest does: 12-20 breaths a minute, the
    # diaphragm 1-2 cm in quiet breathing.
    breathing = load_profile(tmp_path / "adult-chest-breathing.yaml", CaseProfile)
    assert breathing.phases == case.phases and breathing.respiration is not None
    assert 12 <= breathing.respiration.rate_per_min <= 20 and 10 <= breathing.respiration.diaphragm_mm <= 20


def test_unwritable_folder_is_one_line(tmp_path, capsys):
    from appliance.cli import main

    blocker = tmp_path / "file"
    blocker.write_text("")
    assert main(["case", "adult-chest", "--out", str(blocker / "sub"), "--size", "small"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "cannot create the folder" in err[0]


def test_bad_grid_is_refused():
    with pytest.raises(FluorosimError, match="spacing_mm"):
        build_adult_chest((10, 10, 10), (1.0, 0.0, 1.0))


def test_breathing_tells_the_ribs_from_the_scapulae(chest):
    """respiration's default (bone standing taller than a rib is a plate): the scapulae are cut,
    no rib beside the spine is, and no scapula voxel rides on a rib. The ribs and scapulae are
    painted here from adult_skeleton's own rib paths and scapula ellipsoids."""
    from appliance.config.case import Materials, Respiration
    from appliance.patient.adult_body import AnisotropicGrid
    from appliance.patient.adult_skeleton import _rib_path, _vertebrae, spine_y
    from appliance.patient.breathing_motion import BreathingAnatomy, plates
    from appliance.patient.shapes import Layer, ellipsoid, paint_tube, rotation
    from appliance.patient.volume import Volume

    hu, sp, origin = chest
    grid = AnisotropicGrid(hu.shape, sp)
    grid.origin_mm = origin
    painted = Layer(grid, opaque=False)
    for level, v in enumerate(_vertebrae()[:12]):
        pts, _ = _rib_path(level, v[1], float(spine_y(v[1])))
        for s in (-1, 1):
            paint_tube(painted, pts * [-s, 1, 1], 4.0 if level in (0, 10, 11) else 5.0, 1000.0)
    _, X, Y, Z = grid.box((-1e4,) * 3, (1e4,) * 3)
    scapulae = np.zeros(hu.shape, bool)
    for s in (-1, 1):        # adult_skeleton's scapula: centre, semi-axes and turn
        R = rotation("y", -s * 10) @ rotation("z", -s * 28)
        scapulae |= ellipsoid(X, Y, Z, (s * 100.0, 92.0, 95.0), (45.0, 4.0, 70.0), R) < 2.0
    T = np.diag([sp[2], sp[1], sp[0], 1.0])
    T[:3, 3] = origin
    ct = Volume(hu, T, source="adult chest")
    bone = hu >= Materials().bone_min_hu
    ribs, scapulae = bone & (painted.alpha > 0.3) & ~scapulae, bone & scapulae
    p = Respiration()
    cut = plates(np.asarray(ct.hu) >= Materials().bone_min_hu, float(ct.T_ct_from_voxel[2, 2]), ct.spacing_mm,
                 p.rib_max_height_mm, p.rib_plate_widen_mm)
    assert ribs.sum() > 5000 and scapulae.sum() > 1000
    # Beside the spine the vertebrae stand tall (the breathing split takes the spine out first).
    x = ct.T_ct_from_voxel[0, 3] + ct.T_ct_from_voxel[0, 0] * np.arange(ct.hu.shape[2])
    beside = (np.abs(x) > p.spine_half_width_mm + p.rib_plate_widen_mm + ct.spacing_mm[0])[None, None, :]
    assert not cut[ribs & beside].any()
    assert cut[scapulae].mean() > 0.95
    anatomy = BreathingAnatomy(ct, p, Materials())
    held = np.zeros(anatomy.shape, bool)
    for rib in anatomy.ribs:
        held[rib.box] |= rib.alpha > 0
    assert not held[scapulae].any()
