"""The built-in 4D patient against anatomy and physiology known independently of the generator.

Ground truth: Hounsfield units of tissues (air -1000, lung about -850, fat -100, muscle 40,
liver 60, blood 45, disc 80, trabecular 300-400, cortical 1200-1800, urine 0), organ
volumes of a 5-8 year old child, the breathing excursion and VCUG stage volumes the
timeline specifies, and the box phantom's dimensions from its profile.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from appliance.config.case import CaseProfile
from appliance.config.loading import load_profile
from appliance.config.phantom import PhantomProfile
from appliance.errors import FluorosimError
from appliance.patient import builtin, shapes
from appliance.patient.builtin import builtin_phases, iodine_mg_per_ml

ROOT = Path(__file__).resolve().parents[1]
CASE = ROOT / "configs" / "cases" / "child-torso-vcug.yaml"
PHANTOM = ROOT / "configs" / "phantoms" / "box-v1.yaml"


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    root = tmp_path_factory.mktemp("patient-cache")
    messages = []
    phases = builtin_phases("child-torso", root, progress=messages.append)
    return root, phases, messages


@pytest.fixture(scope="module")
def volumes(cache):
    _, phases, _ = cache
    loaded = {}

    def get(k):
        if k not in loaded:
            loaded[k] = phases[k][1]()
        return loaded[k]
    return get


def hu_at(volume, point, half=1):
    """Median HU of the (2*half+1)^3 voxels around a point of the ct frame (mm)."""
    ijk = np.rint(np.linalg.inv(volume.T_ct_from_voxel) @ [*point, 1.0])[:3].astype(int)
    i, j, k = ijk
    return float(np.median(volume.hu[k - half:k + half + 1, j - half:j + half + 1, i - half:i + half + 1]))


def ml_between(volume, lo, hi):
    return float(((volume.hu >= lo) & (volume.hu <= hi)).sum() * np.prod(volume.spacing_mm) / 1000.0)


def test_timeline_has_both_processes_in_order(cache):
    _, phases, messages = cache
    times = [t for t, _ in phases]
    assert len(phases) >= 8
    assert times[0] == 0.0 and all(b > a for a, b in zip(times, times[1:]))
    # One phase a second; the sequence (eight 4 s breaths) is 32 s long.
    assert times[-1] + 1.0 == builtin.SEQUENCE_S == 32.0
    assert any("building" in m for m in messages)


def test_volume_is_int16_lps_and_centred(volumes):
    v = volumes(0)
    assert v.hu.dtype == np.int16 and v.hu.ndim == 3
    assert np.allclose(v.spacing_mm, 1.5)
    assert np.allclose(v.T_ct_from_voxel[:3, :3], np.diag(v.spacing_mm))   # axes along L, P, S
    body = np.argwhere(v.hu > -500)
    lo = (v.T_ct_from_voxel @ np.r_[body.min(axis=0)[::-1], 1.0])[:3]
    hi = (v.T_ct_from_voxel @ np.r_[body.max(axis=0)[::-1], 1.0])[:3]
    size = hi - lo
    # A 5-8 year old: ~220 mm left-right, ~150 mm antero-posterior, ~400 mm of trunk.
    assert 200 <= size[0] <= 235 and 130 <= size[1] <= 150 and 380 <= size[2] <= 400
    assert np.all(np.abs((lo + hi) / 2) < [5, 8, 5])


@pytest.mark.parametrize("point, low, high, tissue", [
    ((0, -80, 0), -1000, -1000, "air in front of the belly"),
    ((-55, 15, 100), -870, -830, "right lung"),
    ((55, 15, 100), -870, -830, "left lung"),
    ((-86.5, -1, -40), -105, -95, "subcutaneous fat at the right flank"),
    ((-78.5, -1, -40), 35, 45, "flank muscle"),
    ((-50, 5, 10), 57, 63, "liver"),
    ((12, -14, 52), 42, 48, "heart (blood)"),
    # T1 starts at z = 172 mm; T1-T12 are 10-12 mm high with 3-4 mm discs (174 mm in all),
    # L1 13.5 mm + 4.5 mm disc, so L2 spans z = -20 to -33.9 and its lower disc is centred
    # at -36.1; lordosis puts the L2 body centre at y = 20 - 6 sin(pi 27 / 96) = 15.4.
    ((0, 15.4, -26.9), 300, 400, "trabecular bone of L2"),
    ((55, -5, -152), 300, 400, "femoral head"),
    ((8, -15, -137), -5, 5, "urine in the drained bladder (beside the catheter)"),
])
def test_tissue_hu_at_known_points(volumes, point, low, high, tissue):
    assert low <= hu_at(volumes(0), point) <= high, tissue


def test_cortical_bone_shell_disc_and_no_bone_in_contrast_range(volumes):
    v = volumes(0)
    assert 70 <= hu_at(v, (0, 15.4, -36.1), half=0) <= 90        # the L2/L3 disc
    # A left-right line through the L2 body meets its cortex twice.
    k = int(round((-26.9 - v.T_ct_from_voxel[2, 3]) / 1.5))
    j = int(round((15.4 - v.T_ct_from_voxel[1, 3]) / 1.5))
    line = v.hu[k, j, :]
    assert 1200 <= line.max() <= 1800
    # The drained bladder holds no contrast: nothing reaches the iodine range.
    assert v.hu.max() < 2500


def test_organ_volumes_of_a_school_age_child(volumes):
    v = volumes(0)
    assert 350 <= ml_between(v, 58, 62) <= 1000       # liver (600-900 mL with its edges)
    assert 25 <= ml_between(v, 48, 52) <= 150         # spleen
    assert 90 <= ml_between(v, 33, 37) <= 220         # both kidneys
    assert 700 <= ml_between(v, -870, -830) <= 2000   # lungs at end-expiration


def _dome_top(volume, x, y):
    """z (mm) where HU falls below -400 going up a vertical line from under the dome into the lung."""
    i = int(round((x - volume.T_ct_from_voxel[0, 3]) / 1.5))
    j = int(round((y - volume.T_ct_from_voxel[1, 3]) / 1.5))
    z0 = volume.T_ct_from_voxel[2, 3]
    profile = volume.hu[:, j - 1:j + 2, i - 1:i + 2].astype(float).mean(axis=(1, 2))
    k = int(round((0 - z0) / 1.5))          # z = 0: in the liver (right) or stomach (left)
    assert profile[k] > -400
    while profile[k + 1] >= -400:
        k += 1
    # Linear interpolation of the crossing between voxel k (tissue) and k + 1 (lung).
    f = (profile[k] + 400) / (profile[k] - profile[k + 1])
    return z0 + 1.5 * (k + f)


def test_diaphragm_moves_by_the_specified_amplitude(volumes):
    expiration, inspiration = volumes(0), volumes(2)     # t = 0 s and t = 2 s of a 4 s breath
    for x, y in ((-50, 5), (55, 5)):                      # the right and left dome apices
        drop = _dome_top(expiration, x, y) - _dome_top(inspiration, x, y)
        assert drop == pytest.approx(12.0, abs=1.0)
    assert _dome_top(expiration, -50, 5) == pytest.approx(45.0, abs=2.0)
    assert _dome_top(expiration, 55, 5) == pytest.approx(33.0, abs=2.0)
    # Mid-inspiration (t = 1 s) lies half way.
    mid = _dome_top(volumes(1), -50, 5)
    assert mid == pytest.approx(45.0 - 6.0, abs=1.0)
    # The liver follows: liver tissue 10 mm below the expiration dome is lung-free in both.
    assert 57 <= hu_at(inspiration, (-50, 5, 45 - 12 - 10)) <= 63


def _manubrium_top(volume):
    """z (mm) of the top of the manubrium (x = 0, y = -53 mm), where HU rises above 300 going down."""
    i = int(round((0 - volume.T_ct_from_voxel[0, 3]) / 1.5))
    j = int(round((-53 - volume.T_ct_from_voxel[1, 3]) / 1.5))
    z0 = volume.T_ct_from_voxel[2, 3]
    profile = volume.hu[:, j - 1:j + 2, i].astype(float).mean(axis=1)
    k = int(round((170 - z0) / 1.5))
    while profile[k] < 300:
        k -= 1
    f = (profile[k] - 300) / (profile[k] - profile[k + 1])
    return z0 + 1.5 * (k + f)


def test_rib_cage_rises_with_inspiration_and_spine_stays(volumes):
    expiration, inspiration = volumes(0), volumes(2)
    # The manubrium (centre 143 mm, 16 mm high) tops out at 151 mm and rises 4 mm.
    assert _manubrium_top(expiration) == pytest.approx(151.0, abs=1.5)
    assert _manubrium_top(inspiration) - _manubrium_top(expiration) == pytest.approx(4.0, abs=0.7)
    # The thoracic spine does not move: T6 (z 95-110 mm) is the same voxel for voxel.
    k0, k1 = (int(round((z - expiration.T_ct_from_voxel[2, 3]) / 1.5)) for z in (95, 110))
    j = int(round((20 - expiration.T_ct_from_voxel[1, 3]) / 1.5))
    assert np.array_equal(expiration.hu[k0:k1, j - 5:j + 5, 70:91], inspiration.hu[k0:k1, j - 5:j + 5, 70:91])


def test_contrast_fills_then_voids(cache, volumes):
    _, phases, _ = cache
    voxel_ml = 1.5 ** 3 / 1000.0
    per_stage = []
    for k in range(0, len(phases), 4):       # end-expiration of each VCUG stage
        v = volumes(k)
        per_stage.append(float(iodine_mg_per_ml(v.hu).sum()) / 150.0 * voxel_ml)
    # The stages' bladder volumes: 10 (drained, no contrast), filled to 80, 160, 250 mL, voided
    # through 235, 160, 80 to a 15 mL residual; the urethra adds ~2-3 mL while voiding.
    expected = [0, 80, 160, 250, 235, 160, 80, 15]
    for got, want in zip(per_stage, expected):
        assert got == pytest.approx(want, rel=0.03, abs=0.5) or (want in (235, 160, 80) and 0 < got - want < 4)
    # The bladder's partial-volume edge is encoded as dilute iodine, never as a HU between
    # bone (<= 1500) and contrast (>= 2500) that the renderer would take for dense bone.
    full = volumes(12).hu
    assert not np.any((full > 1500) & (full < 2510))
    peak = int(np.argmax(per_stage))
    assert peak == 3
    assert all(b > a for a, b in zip(per_stage[:peak], per_stage[1:peak + 1]))
    assert all(b < a for a, b in zip(per_stage[peak:], per_stage[peak + 1:]))


def test_urethra_holds_the_catheter_while_filling_and_contrast_while_voiding(volumes):
    membranous = (0, -20, -172)
    full, voiding = volumes(12), volumes(20)
    # Filling: the catheter (8 Fr, barium-striped, ~600 HU) lies in the collapsed urethra.
    assert 450 <= hu_at(full, membranous, half=0) <= 650
    assert iodine_mg_per_ml(hu_at(voiding, membranous, half=0)) == pytest.approx(150.0, abs=1.0)
    # Bladder centre holds the instilled 150 mg/mL: HU = 2500 + 10 x 150.
    assert hu_at(full, (0, -15, -112), half=1) == 4000


def test_patient_fits_in_the_box(volumes):
    case = load_profile(CASE, CaseProfile)
    box = load_profile(PHANTOM, PhantomProfile).box
    T = np.asarray(case.T_phantom_from_ct, float)
    for k in (0, 2):
        v = volumes(k)
        body = np.argwhere(v.hu > -900)[:, ::-1]
        corners = np.array([[a, b, c] for a in (body[:, 0].min(), body[:, 0].max())
                            for b in (body[:, 1].min(), body[:, 1].max()) for c in (body[:, 2].min(), body[:, 2].max())], float)
        ct = (v.T_ct_from_voxel @ np.c_[corners, np.ones(8)].T)
        phantom = (T @ ct)[:3]
        half = np.array([box.length_mm, box.width_mm, box.height_mm]) / 2 + 0.75   # half a voxel
        assert np.all(np.abs(phantom) <= half[:, None])


def test_shipped_case_agrees_with_the_generator():
    case = load_profile(CASE, CaseProfile)
    assert case.builtin == "child-torso"
    assert case.breathing.period_s == builtin.BREATH_PERIOD_S
    assert case.materials.contrast_min_hu == builtin.CONTRAST_BASE_HU
    assert case.contrast.concentration_mg_per_ml == builtin.CONTRAST_MG_PER_ML


class _Stop(Exception):
    pass


def test_cache_reused_and_a_new_version_rebuilds_atomically(cache, tmp_path, monkeypatch):
    root, phases, _ = cache
    copy = tmp_path / "cache"
    shutil.copytree(root, copy)
    (old,) = [p for p in copy.iterdir() if p.is_dir()]
    stamp = (old / "manifest.json").stat().st_mtime_ns

    messages = []
    again = builtin_phases("child-torso", copy, progress=messages.append)
    assert messages == [] and (old / "manifest.json").stat().st_mtime_ns == stamp
    assert [t for t, _ in again] == [t for t, _ in phases]

    # A new generator version names a new cache folder and starts a build; stopped part
    # way, the build leaves nothing behind and the old cache untouched.
    monkeypatch.setattr(builtin, "GENERATOR_VERSION", builtin.GENERATOR_VERSION + 1)
    started = []

    def stop_at_first_phase(message):
        started.append(message)
        if message.startswith("volume "):
            raise _Stop
    with pytest.raises(_Stop):
        builtin_phases("child-torso", copy, progress=stop_at_first_phase)
    assert "building" in started[0] and builtin.cache_key() not in old.name
    assert sorted(p.name for p in copy.iterdir()) == [old.name]


def test_drawing_is_deterministic(volumes):
    # Draw one phase afresh (a voiding phase at end-inspiration) and compare with the cache.
    spec = builtin.timeline()[22]
    assert (spec.stage, spec.breath) == (5, 1.0)
    fresh = builtin.Builder().phase(spec)
    assert fresh.tobytes() == volumes(22).hu.tobytes()


def test_mistakes_are_one_line_errors(cache, tmp_path):
    with pytest.raises(FluorosimError, match="no built-in patient called 'adult'"):
        builtin_phases("adult", tmp_path)
    not_a_folder = tmp_path / "data"
    not_a_folder.write_text("a file where the data folder should be")
    with pytest.raises(FluorosimError, match="cannot create the cache folder"):
        builtin_phases("child-torso", not_a_folder / "cache")
    root, _, _ = cache
    copy = tmp_path / "cache"
    shutil.copytree(root, copy)
    (folder,) = [p for p in copy.iterdir() if p.is_dir()]
    loaders = builtin_phases("child-torso", copy)
    phase_file = folder / "stage0-breath0000.mha"
    phase_file.write_bytes(phase_file.read_bytes()[:5000])        # truncated, as by a full disk
    with pytest.raises(FluorosimError, match="stage0-breath0000.mha: cannot read this cached phase"):
        loaders[0][1]()
    (folder / "manifest.json").write_text("{not json")
    with pytest.raises(FluorosimError, match="manifest.json: damaged cache"):
        builtin_phases("child-torso", copy)
    manifest = {"phases": [{"time_s": 0.0, "file": "missing.mha"}]}
    (folder / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(FluorosimError, match="missing.mha: missing from the cache"):
        builtin_phases("child-torso", copy)


# --- the drawing primitives, against analytic volumes ---

@pytest.mark.parametrize("shape, exact_mm3", [
    # Sphere r = 10 mm: 4/3 pi r^3.
    (lambda X, Y, Z: shapes.ellipsoid(X, Y, Z, (0.3, -0.2, 0.1), (10, 10, 10)), 4 / 3 * np.pi * 1000),
    # Ellipsoid 14 x 9 x 6 mm, turned 30 degrees about z and 20 about x: 4/3 pi abc.
    (lambda X, Y, Z: shapes.ellipsoid(X, Y, Z, (1, 2, -1), (14, 9, 6), shapes.rotation("z", 30) @ shapes.rotation("x", 20)),
     4 / 3 * np.pi * 14 * 9 * 6),
    # Capsule r = 5 mm, 30 mm between the end centres, oblique: pi r^2 L + 4/3 pi r^3.
    (lambda X, Y, Z: shapes.segment(X, Y, Z, (-10, -8, -15), (10, 8, 6.3), 5, 5),
     np.pi * 25 * np.linalg.norm([20, 16, 21.3]) + 4 / 3 * np.pi * 125),
])
def test_painted_shapes_have_their_analytic_volume(shape, exact_mm3):
    grid = shapes.Grid.centred((41, 41, 41), 1.5)
    layer = shapes.Layer(grid, 0.0)
    layer.paint(shape, 1.0, (-30, -30, -30), (30, 30, 30))
    # Partial-volume edges make the sum of coverages the volume, to well under a voxel layer.
    assert layer.value.sum() * 1.5 ** 3 == pytest.approx(exact_mm3, rel=0.015)


def test_transparent_layer_composites_over_tissue():
    grid = shapes.Grid.centred((11, 11, 11), 1.5)
    bone = shapes.Layer(grid, opaque=False)
    bone.paint(lambda X, Y, Z: X - 0.0, 1000.0, (-10, -10, -10), (10, 10, 10))   # half space x < 0
    below = np.full(grid.shape, 40.0, np.float32)
    out = bone.over(below)
    assert np.allclose(out[..., :5], 1000.0) and np.allclose(out[..., 6:], 40.0)
    assert out[0, 0, 5] == pytest.approx(520.0)      # the voxel the surface halves


def test_build_patient_command_and_previews(cache, volumes, tmp_path, capsys):
    from appliance.cli import main
    from appliance.patient.commands import write_previews
    root, _, _ = cache
    assert main(["build-patient", "--cache", str(root)]) == 0
    assert "32 phases over 32 s" in capsys.readouterr().out
    written = write_previews(volumes(20), tmp_path / "previews", "voiding")
    assert len(written) == 7 and all(p.stat().st_size > 1000 for p in written)
    blocked = tmp_path / "file"
    blocked.write_text("")
    assert main(["build-patient", "--cache", str(root), "--previews", str(blocked / "p")]) == 2
    assert "cannot create the preview folder" in capsys.readouterr().err


def test_controllable_breathing_on_the_builtin_patient(cache, volumes):
    """configs/cases/child-torso-breathing.yaml: the ribs of T6-T12 are found as rigid pieces each
    side beside the spine; the right dome (drawn at z = 45 mm) descends by the tendon's descent;
    the full bladder's contrast stays on its own stage and moves at most by the fall-off's share."""
    from appliance.config.case import CaseProfile
    from appliance.patient.anatomy import RIGHT_DOME
    from appliance.patient.breathing_motion import BreathingAnatomy
    from appliance.patient.builtin import timeline

    case = load_profile(ROOT / "configs" / "cases" / "child-torso-breathing.yaml", CaseProfile)
    specs = timeline()
    rest = volumes(0)
    assert specs[0].breath == 0 and specs[12].breath == 0 and specs[12].stage == 3     # end-expiration, full bladder
    anatomy = BreathingAnatomy(rest, case.respiration, case.materials)
    lower = [r for r in anatomy.ribs if 0.0 < r.head_ct[2] < 90.0]
    assert sorted(r.side for r in lower) == [-1] * 6 + [1] * 6
    assert all(20.0 <= abs(r.head_ct[0]) <= 36.0 for r in lower)
    # All twelve ribs each side, each its own piece, and no voxel of the scapulae (drawn by
    # child_skeleton right on the upper ribs) on any: their plates stand taller than a rib.
    from appliance.patient import child_skeleton
    from appliance.patient.builtin import grid
    from appliance.patient.shapes import Layer
    heads = sorted((r.side, r.head_ct[2]) for r in anatomy.ribs)
    levels = [v.z for v in child_skeleton.vertebrae() if v.name in {f"T{i}" for i in range(1, 13)}]
    for side in (-1, 1):
        zs = [z for s, z in heads if s == side]
        assert len(zs) == 12 and all(min(abs(z - zv) for z in zs) < 5.0 for zv in levels)
    girdle = Layer(grid(), opaque=False)
    child_skeleton._paint_shoulder_girdle(girdle)
    scapulae = (girdle.alpha > 0.5) & (np.asarray(rest.hu) >= case.materials.bone_min_hu)
    held = np.zeros(anatomy.shape, bool)
    for rib in anatomy.ribs:
        held[rib.box] |= rib.alpha > 0
    assert scapulae.sum() > 5000 and not held[scapulae].any()

    def lung_base_z(hu):
        ijk = np.rint(np.linalg.solve(rest.T_ct_from_voxel, [RIGHT_DOME[0], RIGHT_DOME[1], 0.0, 1.0])).astype(int)
        col = hu[:, ijk[1], ijk[0]]
        k = np.flatnonzero(col <= -600).min()         # lowest lung voxel of the column
        return rest.T_ct_from_voxel[2, 3] + rest.T_ct_from_voxel[2, 2] * k
    z0 = lung_base_z(np.asarray(rest.hu))
    assert z0 == pytest.approx(RIGHT_DOME[2], abs=2 * 1.5)
    full = volumes(12)
    moved = anatomy.hu_at(2.0, 3.0, 12.0, anatomy.soft_of(full))
    assert lung_base_z(moved) == pytest.approx(z0 - 12.0, abs=1.5)
    # The bladder's contrast: its neck (where the fall-off has reached 0) stays; its top moves
    # down by no more than the fall-off's share of the descent there.
    z_k = rest.T_ct_from_voxel[2, 3] + rest.T_ct_from_voxel[2, 2] * np.arange(rest.hu.shape[0])
    before = z_k[np.nonzero((np.asarray(full.hu) >= 2500).any(axis=(1, 2)))[0]]
    after = z_k[np.nonzero((moved >= 2500).any(axis=(1, 2)))[0]]
    assert after.min() == pytest.approx(before.min(), abs=1.5)
    assert 0.0 <= before.max() - after.max() <= 12.0 * float(anatomy.weight_z(before.max())) + 1.5
