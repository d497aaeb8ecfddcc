"""The sphere phantom as a CT volume, so the project's DRR renderer can X-ray it.

Each voxel gets the fraction of it that lies inside a ball (4x4x4 sub-samples), and the
plates their PMMA number, so a 2 mm ball on a 0.5 mm grid keeps its centre to a few
hundredths of a millimetre. The CT frame of the volume is the phantom frame, so a phantom
pose is directly the renderer's T_xray_from_ct.
"""

from __future__ import annotations

import numpy as np

from ...config.calibration_phantom import CalibrationPhantomProfile
from ...config.fluoroscope import FluoroscopeProfile
from ...patient.volume import Volume
from .shadowgraph import burn_in_text

AIR_HU = -1000
SUBSAMPLES = 4


def ball_fractions(centre_vox: np.ndarray, radius_vox: float, shape_zyx: tuple[int, int, int]):
    """(slices, fraction array) of the voxels a ball of `radius_vox` at `centre_vox` (i, j, k) touches."""
    lo = np.maximum(np.floor(centre_vox - radius_vox - 1).astype(int), 0)
    hi = np.minimum(np.ceil(centre_vox + radius_vox + 1).astype(int) + 1, np.array(shape_zyx[::-1]))
    sub = (np.arange(SUBSAMPLES) + 0.5) / SUBSAMPLES - 0.5
    axes = [(np.arange(lo[a], hi[a])[:, None] + sub[None, :]).reshape(-1) - centre_vox[a] for a in range(3)]
    di, dj, dk = axes
    inside = (dk[:, None, None] ** 2 + dj[None, :, None] ** 2 + di[None, None, :] ** 2) <= radius_vox ** 2
    n = [hi[a] - lo[a] for a in range(3)]
    frac = inside.reshape(n[2], SUBSAMPLES, n[1], SUBSAMPLES, n[0], SUBSAMPLES).mean(axis=(1, 3, 5))
    return (slice(lo[2], hi[2]), slice(lo[1], hi[1]), slice(lo[0], hi[0])), frac


def phantom_volume(phantom: CalibrationPhantomProfile, voxel_mm: float = 0.5, margin_mm: float = 2.0) -> Volume:
    """The phantom voxelised on an axis-aligned grid of `voxel_mm`, in the phantom frame (mm)."""
    length = max(p.length_mm for p in phantom.plates)
    width = max(p.width_mm for p in phantom.plates)
    z_lo = min(p.centre_z_mm - p.thickness_mm / 2 for p in phantom.plates)
    z_hi = max(p.centre_z_mm + p.thickness_mm / 2 for p in phantom.plates)
    lo = np.array([-length / 2 - margin_mm, -width / 2 - margin_mm, z_lo - margin_mm])
    hi = np.array([length / 2 + margin_mm, width / 2 + margin_mm, z_hi + margin_mm])
    n = np.ceil((hi - lo) / voxel_mm).astype(int) + 1
    T = np.eye(4)
    T[:3, :3] = np.diag([voxel_mm] * 3)
    T[:3, 3] = lo
    centres_x = lo[0] + voxel_mm * np.arange(n[0])
    centres_y = lo[1] + voxel_mm * np.arange(n[1])
    centres_z = lo[2] + voxel_mm * np.arange(n[2])
    hu = np.full((n[2], n[1], n[0]), float(AIR_HU), np.float32)
    m = phantom.materials
    for p in phantom.plates:
        # Partial-volume coverage of each axis, so a plate face between voxel centres is exact on average.
        cover = [_coverage(centres_x, -p.length_mm / 2, p.length_mm / 2, voxel_mm),
                 _coverage(centres_y, -p.width_mm / 2, p.width_mm / 2, voxel_mm),
                 _coverage(centres_z, p.centre_z_mm - p.thickness_mm / 2, p.centre_z_mm + p.thickness_mm / 2, voxel_mm)]
        f = cover[2][:, None, None] * cover[1][None, :, None] * cover[0][None, None, :]
        hu += f * (m.plate_hu - AIR_HU)
    for c, d in zip(phantom.centres(), phantom.diameters()):
        where, frac = ball_fractions((c - lo) / voxel_mm, d / 2 / voxel_mm, hu.shape)
        hu[where] += frac * (m.sphere_hu - hu[where])
    return Volume(np.round(hu).astype(np.int16), T, source=f"{phantom.name}, {voxel_mm} mm voxels")


def _coverage(centres: np.ndarray, a: float, b: float, voxel_mm: float) -> np.ndarray:
    """Fraction of each voxel (1-D, centred at `centres`) inside [a, b]."""
    lo, hi = centres - voxel_mm / 2, centres + voxel_mm / 2
    return np.clip((np.minimum(hi, b) - np.maximum(lo, a)) / voxel_mm, 0.0, 1.0)


def machine_profile(fluoroscope: FluoroscopeProfile, K: np.ndarray, dist: np.ndarray) -> FluoroscopeProfile:
    """`fluoroscope` with its intrinsics replaced by the given camera matrix and distortion."""
    d = dict(zip(("k1", "k2", "p1", "p2", "k3"), (float(x) for x in dist)))
    intr = fluoroscope.intrinsics.model_copy(update=dict(
        fx=float(K[0, 0]), fy=float(K[1, 1]), cx=float(K[0, 2]), cy=float(K[1, 2]),
        distortion=fluoroscope.intrinsics.distortion.model_copy(update=d)))
    return fluoroscope.model_copy(update=dict(intrinsics=intr))


def render_phantom_images(phantom: CalibrationPhantomProfile, fluoroscope: FluoroscopeProfile, machine,
                          poses: list[np.ndarray], rng: np.random.Generator, voxel_mm: float = 0.5,
                          device: str = "auto"):
    """X-ray images of the phantom at `poses` (T_xray_from_phantom) made by the project's DRR
    renderer with the true machine's K and distortion: what the monitor shows (inverted, so
    air is bright as on a clinical frame grab), with noise, focal-spot blur, vignetting, the
    intensifier circle and burned-in text. Returns (images, circle centre (u, v), radius px)."""
    from ...config.case import Materials
    from ...xray.renderer import Renderer, View

    true_profile = machine_profile(fluoroscope, machine.K, machine.dist)
    # Calibration exposures are taken at a fixed technique (ABC locked), as on the real unit:
    # the thin plate and its steel balls would otherwise be windowed to the plate alone.
    true_profile = true_profile.model_copy(update={"abc": true_profile.abc.model_copy(update={"enabled": False})})
    renderer = Renderer(true_profile, Materials(), device=device)
    prepared = renderer.prepare(phantom_volume(phantom, voxel_mm))
    images = []
    for T in poses:
        seed = int(rng.integers(2 ** 31))
        image = renderer.render(prepared, T, View(zoom=1, invert=True, noise=True, quantity="display", seed=seed))
        burn_in_text(image)
        images.append(image)
    det = fluoroscope.detector
    radius = fluoroscope.zoom_levels[0].fov_mm / det.pixel_pitch_mm / 2.0
    return images, ((det.columns - 1) / 2.0, (det.rows - 1) / 2.0), radius
