"""A synthetic adult chest and upper abdomen CT, in Hounsfield units, for tests and benchmarks.

The built-in patient is a child; an image chain tuned on a child alone fails on an adult,
whose mediastinum and spine let through a hundred times fewer photons and whose lungs let
through more. This draws a 45-year-old man of average build from the lung apices down to
the upper poles of the kidneys: skin, subcutaneous fat, chest-wall muscle, 12 pairs of ribs
with a cortical shell and costal cartilage, sternum, clavicles, scapulae, the spine T1-L2
(cortex, cancellous bone, discs, posterior elements, canal), lungs with branching
pulmonary vessels and bronchi, heart with pericardial fat, aorta, trachea, diaphragm domes
(the right higher), liver, spleen, stomach with its gas bubble, kidneys and colon with gas.
The body's tissue values and surfaces are in `adult_body.py`, the bones in `adult_skeleton.py`;
this module draws the organs and writes the CT and its case profile.

The grid may be anisotropic, as a clinical CT is (2.5 mm slices, 0.8 mm pixels); any
shape and spacing cover the same body, centred in the grid, so a small grid is the same
patient at coarse resolution. Coordinates are the `ct` frame of DESIGN.md (LPS, mm):
x toward the patient's left, y posterior, z superior.

    python -m appliance.patient.adult_chest --out DIR [--small]

writes `adult-chest.mha` and a case profile `adult-chest.yaml` beside it.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from ..atomic_file import write_atomic
from ..errors import FluorosimError
from .adult_body import (
    HU_AIR,
    HU_BLOOD,
    HU_BOWEL,
    HU_FAT,
    HU_FLUID,
    HU_KIDNEY,
    HU_LIVER,
    HU_LUNG,
    HU_LUNG_DEPENDENT_RISE,
    HU_MEDIASTINUM,
    HU_MUSCLE,
    HU_MYOCARDIUM,
    HU_NOISE,
    HU_SKIN,
    HU_SPLEEN,
    SKIN_MM,
    SUBCUT_FAT_MM,
    AnisotropicGrid,
    cavity,
    diaphragm_z,
    lung,
    skin,
)
from .adult_skeleton import paint_ribs_and_sternum, paint_spine
from .shapes import Layer, bounds, ellipsoid, elliptic_prism, intersect, paint_tube, rotation

#: Pulmonary vessels: a branch splits while its radius is above this (mm); Murray's law
#: gives children of 2^(-1/3) of the parent's radius.
VESSEL_MIN_RADIUS_MM = 0.7


# --- airways and pulmonary vessels ---

def _tree(rng, start, direction, radius, length, side, out, depth=0):
    """Grow a bifurcating tube tree from `start`, appending (p, q, r0, r1) segments to `out`."""
    direction = direction / np.linalg.norm(direction)
    end = start + direction * length
    if lung(*(np.float32(v) for v in end), side) > 0 or depth > 12:
        end = start + direction * length * 0.5
        out.append((start, end, radius, radius * 0.8))
        return
    out.append((start, end, radius, radius * 0.9))
    if radius < VESSEL_MIN_RADIUS_MM:
        return
    # Two children about 35 degrees apart in a random plane through the parent's axis.
    helper = np.array([0.0, 0.0, 1.0]) if abs(direction[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    u = np.cross(direction, helper)
    u /= np.linalg.norm(u)
    w = np.cross(direction, u)
    phi = rng.uniform(0, 2 * np.pi)
    plane = np.cos(phi) * u + np.sin(phi) * w
    rng.uniform(0.45, 0.55)          # a draw kept so that each seed keeps the tree it always had
    for sign in (1, -1):
        angle = np.radians(rng.uniform(25, 42))
        child = np.cos(angle) * direction + sign * np.sin(angle) * plane
        r = radius * 2 ** (-1 / 3) * (1.0 + rng.uniform(-0.1, 0.1))
        _tree(rng, end, child, r, length * rng.uniform(0.72, 0.88), side, out, depth + 1)


def _lung_clip(side):
    return lambda X, Y, Z: lung(X, Y, Z, side) + 0.5


def _paint_lungs(layer: Layer, rng) -> None:
    for side in (-1, 1):
        layer.paint(lambda X, Y, Z, s=side: lung(X, Y, Z, s), 0.0, (-200, -150, -120), (200, 150, 200))
    # Aerated lung, denser toward the back; painted as an offset added in place.
    region = layer.grid.box((-200, -150, -120), (200, 150, 200))
    sl, X, Y, Z = region
    inside = np.clip(0.5 - np.minimum(lung(X, Y, Z, -1), lung(X, Y, Z, 1)) / layer.grid.spacing_mm, 0, 1)
    dependent = HU_LUNG + HU_LUNG_DEPENDENT_RISE * np.clip((Y + 100.0) / 200.0, 0, 1)
    v = layer.value[sl]
    v += inside * (dependent - v)
    # Pulmonary arteries and veins from each hilum toward the upper, middle and lower lung.
    for side in (-1, 1):
        hilum = np.array([side * 62.0, 10.0, 45.0])
        segments: list = []
        for target in ((side * 70, -40, 130), (side * 110, 20, 90), (side * 100, -60, 30), (side * 110, 40, 10),
                       (side * 80, 60, -20), (side * 120, -20, -10), (side * 60, 40, 120)):
            d = np.array(target, float) - hilum
            _tree(rng, hilum.copy(), d, 5.5, 0.32 * np.linalg.norm(d), side, segments)
        clip = _lung_clip(side)
        for p, q, r0, r1 in segments:
            paint_tube(layer, [p, q], [r0, r1], HU_BLOOD, clip=clip)
    # Trachea, carina and main bronchi: air with a soft-tissue wall.
    airway = [(0.0, 0.0, 200.0), (0.0, 8.0, 120.0), (0.0, 12.0, 75.0)]
    paint_tube(layer, airway, 11.0, HU_MUSCLE)
    paint_tube(layer, airway, 9.0, HU_AIR)
    for side in (-1, 1):
        bronchus = [(0.0, 12.0, 75.0), (side * 30.0, 14.0, 62.0), (side * 55.0, 16.0, 50.0 - 5 * (side > 0))]
        paint_tube(layer, bronchus, 7.5, HU_MUSCLE)
        paint_tube(layer, bronchus, 5.5, HU_AIR)
        lobar = [(side * 55.0, 16.0, 50.0), (side * 75.0, 22.0, 20.0)]
        paint_tube(layer, lobar, 5.0, HU_MUSCLE, clip=_lung_clip(side))
        paint_tube(layer, lobar, 3.5, HU_AIR, clip=_lung_clip(side))


# --- mediastinum and abdomen ---

def _paint_mediastinum(layer: Layer) -> None:
    heart_c = (22.0, -25.0, 5.0)
    R = rotation("y", -35) @ rotation("z", -20)
    layer.paint(lambda X, Y, Z: ellipsoid(X, Y, Z, heart_c, (75.0, 58.0, 62.0), R), HU_FAT, *bounds([heart_c], 85))
    layer.paint(lambda X, Y, Z: ellipsoid(X, Y, Z, heart_c, (70.0, 53.0, 57.0), R), HU_MYOCARDIUM, *bounds([heart_c], 80))
    layer.paint(lambda X, Y, Z: ellipsoid(X, Y, Z, (heart_c[0] + 8, heart_c[1], heart_c[2] + 5), (50.0, 38.0, 42.0), R),
                HU_BLOOD, *bounds([heart_c], 70))
    # Aorta: ascending from the heart, the arch over the left bronchus, descending left of the spine.
    aorta = [(5.0, -20.0, 40.0), (2.0, -22.0, 85.0), (5.0, -5.0, 110.0), (22.0, 25.0, 105.0),
             (26.0, 40.0, 80.0), (22.0, 42.0, 0.0), (12.0, 32.0, -90.0), (5.0, 22.0, -200.0)]
    paint_tube(layer, aorta, (15.0, 15.0, 14.0, 13.0, 13.0, 12.0, 11.0, 10.0), HU_BLOOD)
    paint_tube(layer, [(-25.0, -15.0, 130.0), (-25.0, -12.0, 40.0)], 10.0, HU_BLOOD)      # superior vena cava
    paint_tube(layer, [(-5.0, -30.0, 35.0), (-12.0, 0.0, 60.0), (-55.0, 8.0, 47.0)], (14.0, 12.0, 9.0), HU_BLOOD)
    paint_tube(layer, [(-12.0, 0.0, 60.0), (12.0, 5.0, 65.0), (58.0, 10.0, 52.0)], (12.0, 11.0, 9.0), HU_BLOOD)
    paint_tube(layer, [(-20.0, 5.0, -200.0), (-22.0, 5.0, -30.0), (-18.0, 0.0, 0.0)], 13.0, HU_BLOOD)    # IVC
    paint_tube(layer, [(0.0, 20.0, 60.0), (12.0, 35.0, -50.0), (8.0, 30.0, -90.0)], 7.0, HU_MUSCLE)      # oesophagus


def _paint_abdomen(layer: Layer, rng) -> None:
    every = (-200, -150, -250), (200, 150, 100)
    below = lambda X, Y, Z, inset=0.0: intersect(cavity(X, Y, Z) + inset, Z - (diaphragm_z(X, Y) - inset))
    layer.paint(below, HU_BOWEL, *every)
    # The liver fills the right upper quadrant under the right dome, its lower edge rising to the left.
    layer.paint(lambda X, Y, Z: intersect(below(X, Y, Z, 4.0), X - 40.0 + 0.3 * (Y + 40), -140.0 - Z + 0.25 * (X + 100)),
                HU_LIVER, *every)
    spleen_c = (105.0, 45.0, -60.0)
    layer.paint(lambda X, Y, Z: intersect(ellipsoid(X, Y, Z, spleen_c, (30.0, 55.0, 50.0), rotation("z", 35)), below(X, Y, Z, 3.0)),
                HU_SPLEEN, *bounds([spleen_c], 60))
    stomach_c = (60.0, -35.0, -60.0)
    Rs = rotation("y", 25)
    layer.paint(lambda X, Y, Z: intersect(ellipsoid(X, Y, Z, stomach_c, (50.0, 40.0, 60.0), Rs), below(X, Y, Z, 3.0)),
                HU_MUSCLE, *bounds([stomach_c], 70))
    layer.paint(lambda X, Y, Z: intersect(ellipsoid(X, Y, Z, stomach_c, (45.0, 35.0, 55.0), Rs), below(X, Y, Z, 7.0)),
                HU_FLUID, *bounds([stomach_c], 65))
    # The gas bubble of the fundus rises to the top (anterior, supine; superior on an erect film).
    layer.paint(lambda X, Y, Z: intersect(ellipsoid(X, Y, Z, stomach_c, (45.0, 35.0, 55.0), Rs), below(X, Y, Z, 7.0),
                                          Y - (stomach_c[1] - 15.0)), HU_AIR, *bounds([stomach_c], 65))
    for s in (-1, 1):
        kc = (s * 75.0, 55.0, -165.0 + (10.0 if s > 0 else 0.0))
        layer.paint(lambda X, Y, Z, c=kc, s=s: ellipsoid(X, Y, Z, c, (28.0, 25.0, 55.0), rotation("y", s * 12)), HU_KIDNEY,
                    *bounds([kc], 60))
    # Colon: the hepatic and splenic flexures and transverse colon, with gas pockets.
    colon = [(-110.0, 10.0, -200.0), (-100.0, -20.0, -120.0), (-40.0, -60.0, -140.0),
             (40.0, -60.0, -130.0), (105.0, -10.0, -95.0), (115.0, 20.0, -200.0)]
    paint_tube(layer, colon, 24.0, HU_BOWEL, clip=lambda X, Y, Z: below(X, Y, Z, 2.0))
    pts = np.array(colon)
    for _ in range(18):
        k = rng.integers(0, len(pts) - 1)
        t = rng.uniform(0, 1)
        c = pts[k] + t * (pts[k + 1] - pts[k]) + rng.normal(0, 5, 3)
        radii = rng.uniform(8, 18, 3)
        layer.paint(lambda X, Y, Z, c=c, r=radii: intersect(ellipsoid(X, Y, Z, c, r), below(X, Y, Z, 4.0)),
                    HU_AIR, *bounds([c], 20))
    # Paraspinal muscles behind the spine, the whole height.
    for s in (-1, 1):
        c = (s * 35.0, 95.0, 0.0)
        layer.paint(lambda X, Y, Z, c=c: intersect(elliptic_prism(X, Y, Z, c, 32.0, 22.0, 300.0), skin(X, Y, Z, SKIN_MM + SUBCUT_FAT_MM)),
                    HU_MUSCLE, *bounds([c], 310))


def build_adult_chest(shape_zyx=(136, 512, 512), spacing_mm=(2.5, 0.8, 0.8), seed=0,
                      origin_mm=None, ct_noise=True):
    """The adult chest CT on a grid of `shape_zyx` voxels of `spacing_mm` (z, y, x; mm).

    Returns (hu, spacing_mm, origin_mm): int16 HU indexed [z, y, x]; the spacing (z, y, x)
    as given; the LPS position (x, y, z; mm) of voxel [0, 0, 0]. The body is centred in the
    grid unless `origin_mm` places voxel [0, 0, 0] (a part of the same patient on a finer
    grid: the same seed draws the same vessels and gas); `seed` picks the vessel branching,
    bowel gas and CT noise; `ct_noise` False leaves the CT's own noise out (the anatomy alone).
    """
    rng = np.random.default_rng(seed)
    grid = AnisotropicGrid(shape_zyx, spacing_mm, "adult chest")
    if origin_mm is not None:
        grid.origin_mm = tuple(float(o) for o in origin_mm)
    layer = Layer(grid, HU_AIR)
    every = (-1e4, -1e4, -1e4), (1e4, 1e4, 1e4)
    _, X, Y, Z = grid.box(*every)
    outer = skin(X, Y, Z)
    layer.paint(lambda *box: outer, HU_SKIN, *every)
    layer.paint(lambda *box: outer + np.float32(SKIN_MM), HU_FAT, *every)
    layer.paint(lambda *box: outer + np.float32(SKIN_MM + SUBCUT_FAT_MM), HU_MUSCLE, *every)
    layer.paint(cavity, HU_MEDIASTINUM, *every)
    _paint_abdomen(layer, rng)
    _paint_lungs(layer, rng)
    _paint_mediastinum(layer)
    paint_ribs_and_sternum(layer)
    paint_spine(layer)
    hu = layer.value
    if ct_noise:
        hu += rng.normal(0.0, HU_NOISE, hu.shape).astype(np.float32)
    out = np.clip(np.rint(hu), -1024, 3071).astype(np.int16)
    return out, tuple(float(s) for s in spacing_mm), tuple(float(o) for o in grid.origin_mm)


#: Demographics of the drawn patient, for the case profile's dose reports.
CASE_YAML = """\
# A synthetic adult chest and upper abdomen CT ({shape} voxels of {spacing} mm, z y x),
# drawn by appliance/patient/adult_chest.py with seed {seed}.
title: Adult chest - synthetic CT{breathing}
description: Adult chest and upper abdomen; ribs, spine, lung vessels, heart, diaphragm.
phases:
  - volume: {volume}
    time_s: 0
at_end: hold
{respiration}# The patient lies supine along the box: superior toward phantom +x, posterior toward the
# box floor (phantom -z), the patient's left toward phantom -y.
T_phantom_from_ct:
  - [0, 0, 1, 0]
  - [-1, 0, 0, 0]
  - [0, -1, 0, 0]
  - [0, 0, 0, 1]
materials:
  air_max_hu: -800
  bone_min_hu: 300
  bone_density_at_1000_hu_g_per_cm3: 1.6
patient:
  sex: M
  age_years: 45
  weight_kg: 80
  height_m: 1.78
"""

#: The breathing the second profile, adult-chest-breathing.yaml, gives the same CT: an adult's
#: quiet breathing, the diaphragm's 1.5 cm at 15 breaths a minute, with the schema's rib angles.
RESPIRATION_YAML = """\
respiration:
  diaphragm_mm: 15              # quiet breathing of an adult: 1-2 cm
  rate_per_min: 15              # an adult at rest breathes 12-20 times a minute
"""

#: Grids the command writes: the clinical one, and a quick one for tests and benches.
SIZES = {"full": ((136, 512, 512), (2.5, 0.8, 0.8)), "small": ((68, 128, 128), (5.0, 3.2, 3.2))}


def write_adult_chest(out_dir: str | Path, size: str = "full", seed: int = 0, suffix: str = ".mha") -> Path:
    """Write the CT as `adult-chest<suffix>` (.mha, .nii or .nii.gz) and its case profile
    `adult-chest.yaml` into `out_dir`; returns the profile's path."""
    import SimpleITK as sitk

    shape, spacing = SIZES[size]
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise FluorosimError(f"{out}: cannot create the folder ({e.strerror or e}); choose another --out") from None
    hu, spacing, origin = build_adult_chest(shape, spacing, seed)
    image = sitk.GetImageFromArray(hu)
    image.SetSpacing((spacing[2], spacing[1], spacing[0]))
    image.SetOrigin(origin)
    volume = out / f"adult-chest{suffix}"
    try:
        sitk.WriteImage(image, str(volume), True)
    except (OSError, RuntimeError) as e:
        raise FluorosimError(f"{volume}: cannot write the CT ({str(e).strip().splitlines()[-1][:120]}); "
                             "check the folder and free space") from None
    return write_profiles(volume, shape, spacing, seed)


def write_profiles(volume: Path, shape=SIZES["full"][0], spacing=SIZES["full"][1], seed: int = 0) -> Path:
    """Write the case profiles of the CT `volume` beside it: adult-chest.yaml (one phase, held)
    and adult-chest-breathing.yaml (the same CT, breathing as RESPIRATION_YAML says). Returns
    the first's path."""
    profile = volume.parent / "adult-chest.yaml"
    text = dict(shape="x".join(map(str, shape)), spacing="/".join(map(str, spacing)), seed=seed, volume=volume.name)
    # Whole or not at all: a profile cut short by a full disk would stand in the cache for the next run.
    write_atomic(profile, CASE_YAML.format(**text, breathing="", respiration="").encode())
    write_atomic(profile.with_name("adult-chest-breathing.yaml"),
                 CASE_YAML.format(**text, breathing=", breathing", respiration=RESPIRATION_YAML).encode())
    return profile


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m appliance.patient.adult_chest", description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", required=True, metavar="DIR", help="folder for adult-chest.mha and adult-chest.yaml")
    parser.add_argument("--size", choices=sorted(SIZES), default="full", help="full: 136x512x512 at 2.5/0.8/0.8 mm; small: 68x128x128")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--format", choices=(".mha", ".nii.gz", ".nii"), default=".mha")
    args = parser.parse_args(argv)
    try:
        print(write_adult_chest(args.out, args.size, args.seed, args.format))
    except FluorosimError as e:
        print(f"adult chest: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
