"""Placing a CT in the box phantom: the `T_phantom_from_ct` that puts a chosen point of the
patient at the X-ray isocentre, with the patient lying the way the beam should see it.

The isocentre is found, not assumed: the fluoroscope's principal ray (the xray frame's +z
axis) at `source_to_isocentre_mm`, taken through `T_xray_from_webcam` and the demo path's
home pose `T_webcam_from_phantom` into the phantom frame. Because the webcam sits off the
beam axis, that point is not the box's centre (with the shipped profiles it lies about
150 mm from it along the box), which is why "move the target to the box centre" misses.

Orientation, with the box's long axis (phantom +x) toward the patient's head:
- PA: the patient supine, posterior toward the source (an under-couch tube sees the back first);
- AP: the patient prone, anterior toward the source;
- LAT: the patient on the right side, the left side toward the detector (a left lateral).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..config.fluoroscope import FluoroscopeProfile
from ..geometry import apply, invert, make_transform
from .volume import Volume

BEAMS = ("PA", "AP", "LAT")
#: Box axis the patient's head points along (phantom frame).
HEAD_AXIS_PHANTOM = np.array([1.0, 0.0, 0.0])


@dataclass(frozen=True)
class BeamGeometry:
    """The X-ray beam at the home pose, in the phantom frame (mm)."""

    T_xray_from_phantom: np.ndarray
    isocentre: np.ndarray      # (3,) the point on the principal ray at source_to_isocentre_mm
    source: np.ndarray         # (3,) the focal spot
    direction: np.ndarray      # (3,) unit vector of the principal ray, source toward detector
    field_radius_mm: float     # radius of the widest field at the isocentre plane (mm)
    source_to_isocentre_mm: float
    source_to_image_mm: float


def beam_geometry(fluoroscope: FluoroscopeProfile, T_webcam_from_phantom: np.ndarray) -> BeamGeometry:
    T_xray_from_phantom = fluoroscope.T_xray_from_webcam() @ T_webcam_from_phantom
    T_phantom_from_xray = invert(T_xray_from_phantom)
    sod = fluoroscope.geometry.source_to_isocentre_mm
    sid = fluoroscope.geometry.source_to_image_mm
    iso = apply(T_phantom_from_xray, np.array([0.0, 0.0, sod]))
    source = apply(T_phantom_from_xray, np.zeros(3))
    direction = T_phantom_from_xray[:3, :3] @ np.array([0.0, 0.0, 1.0])
    radius = 0.5 * fluoroscope.zoom_levels[0].fov_mm * sod / sid
    return BeamGeometry(T_xray_from_phantom, iso, source, direction, radius, sod, sid)


def rotation_phantom_from_ct(beam: str, direction: np.ndarray) -> np.ndarray:
    """R_phantom_from_ct for a patient seen by `beam` (PA, AP or LAT) along `direction`."""
    d = np.asarray(direction, float) / np.linalg.norm(direction)
    head = HEAD_AXIS_PHANTOM - (HEAD_AXIS_PHANTOM @ d) * d
    if np.linalg.norm(head) < 1e-6:
        raise ValueError("the beam runs along the box's long axis; the patient cannot lie along the box")
    head /= np.linalg.norm(head)
    # Columns are where the CT's x (left), y (posterior) and z (superior) axes point.
    if beam == "PA":
        posterior = -d
        left = np.cross(posterior, head)
    elif beam == "AP":
        posterior = d
        left = np.cross(posterior, head)
    elif beam == "LAT":
        left = d
        posterior = np.cross(head, left)
    else:
        raise ValueError(f"beam must be one of {', '.join(BEAMS)}, not {beam!r}")
    return np.stack([left, posterior, head], axis=1)


def place(target_lps, beam: str, geometry: BeamGeometry) -> np.ndarray:
    """T_phantom_from_ct mapping `target_lps` (ct frame, mm) onto the isocentre."""
    R = rotation_phantom_from_ct(beam, geometry.direction)
    return make_transform(R, geometry.isocentre - R @ np.asarray(target_lps, float))


@dataclass(frozen=True)
class Coverage:
    """How much of the field at the isocentre the CT fills, along the two axes across the beam."""

    short_mm: dict[str, float]   # side ('head', 'feet', 'across+', 'across-') -> mm of field beyond the CT


def coverage(volume: Volume, T_phantom_from_ct: np.ndarray, geometry: BeamGeometry) -> Coverage:
    """Per side of the field (radius at the isocentre plane), how far the field runs past the CT's end."""
    nx, ny, nz = volume.shape_xyz
    corners = np.array([[i, j, k] for i in (0, nx - 1) for j in (0, ny - 1) for k in (0, nz - 1)], float)
    ph = apply(T_phantom_from_ct @ volume.T_ct_from_voxel, corners) - geometry.isocentre
    d = geometry.direction / np.linalg.norm(geometry.direction)
    head = HEAD_AXIS_PHANTOM - (HEAD_AXIS_PHANTOM @ d) * d
    head /= np.linalg.norm(head)
    across = np.cross(d, head)
    r = geometry.field_radius_mm
    short = {}
    for name, axis in (("head", head), ("across", across)):
        s = ph @ axis
        short[f"{name}+"] = max(0.0, r - float(s.max()))
        short[f"{name}-"] = max(0.0, r + float(s.min()))
    return Coverage(short)
