"""The C-arm's positioner angles (DICOM Positioner Primary and Secondary Angle) from a pose.

DICOM (PS3.3, the XA Positioner module) gives the direction of the X-ray beam, from the
source to the detector, as two angles about the patient: the primary angle from RAO to LAO
(about the patient's head-foot axis; LAO positive), the secondary from caudal to cranial
(CRA positive), both 0 for the beam straight from posterior to anterior with the patient
supine (the detector over the chest: the usual "AP" C-arm view). In the patient's LPS frame
(the `ct` frame: +x left, +y posterior, +z head) the beam direction d is then

    d = (sin(primary) cos(secondary), -cos(primary) cos(secondary), sin(secondary))

so primary = atan2(d_x, -d_y) in (-180, 180] and secondary = asin(d_z) in [-90, 90] (deg).
The beam is the xray frame's +z axis (the principal ray, focal spot toward the detector):
in the ct frame it is the third row of T_xray_from_ct's rotation.
"""

from __future__ import annotations

import math

import numpy as np


def positioner_angles(T_xray_from_ct: np.ndarray) -> tuple[float, float]:
    """(primary, secondary) positioner angles of the beam of pose `T_xray_from_ct` (deg)."""
    d = np.asarray(T_xray_from_ct, dtype=np.float64)[2, :3]
    d = d / np.linalg.norm(d)
    primary = math.degrees(math.atan2(d[0], -d[1]))
    secondary = math.degrees(math.asin(max(-1.0, min(1.0, float(d[2])))))
    # atan2 gives -180 for a beam along +y with a rounding sign; DICOM's range ends at +180.
    return (180.0 if primary <= -180.0 + 1e-9 else primary), secondary
