"""Saved images: what the trainee saw when pressing save, as PNG and as a DICOM image.

The DICOM file is an X-Ray Radiofluoroscopic Image (RF) whose standard tags carry the
geometry and exposure of the moment: KVP, tube current, pulse width and radiation mode, the
source-to-detector and source-to-isocentre distances, the intensifier field of view and its
shape, the imager pixel spacing at that zoom, the collimator blades in image pixels, and the
session's cumulative fluoroscopy time and dose-area product. Pixels are display values
(after window, level and invert), so Pixel Intensity Relationship is DISP.

Every image belongs to its session's study (records.study): the same Study Instance UID,
patient and equipment as the session's dose report, and the Irradiation Event UID of the run
it shows.
"""

from __future__ import annotations

import datetime as dt
from pathlib import Path

import cv2
import numpy as np
from pydicom.dataset import Dataset
from pydicom.uid import XRayRadiofluoroscopicImageStorage

from ..atomic_file import write_atomic
from ..config.fluoroscope import FluoroscopeProfile
from ..console.state import ConsoleState
from ..errors import FluorosimError
from .dicom import ds_number as _ds_number
from .dicom import encode
from .positioner import positioner_angles
from .study import SessionStudy, apply_common, person_name, procedure_step_reference


def _as_display(image: np.ndarray) -> np.ndarray:
    """A 2-D uint8 or uint16 image; floats are taken as 0..1 display values."""
    a = np.asarray(image)
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[:, :, 0]
    if a.ndim != 2:
        raise ValueError(f"a saved image must be grey-scale (rows, columns), got shape {a.shape}")
    if a.dtype == np.uint8 or a.dtype == np.uint16:
        return a
    if np.issubdtype(a.dtype, np.floating):
        return np.asarray(np.round(np.clip(np.nan_to_num(a), 0.0, 1.0) * 255.0), dtype=np.uint8)
    raise ValueError(f"unsupported image type {a.dtype}; give uint8, uint16 or float in 0..1")


def dicom_image(pixels: np.ndarray, state: ConsoleState, fl: FluoroscopeProfile, *, t_wall: float,
                study: SessionStudy, event_uid: str | None, T_xray_from_ct: np.ndarray | None = None) -> Dataset:
    """The RF image of one save; `event_uid` is the Irradiation Event UID of the run it shows,
    `T_xray_from_ct` the pose of the C-arm to the patient it was rendered at (None: unknown)."""
    rows, cols = pixels.shape
    when = dt.datetime.fromtimestamp(t_wall, tz=dt.UTC)
    # The field of view fills the image: this zoom's pixel size at the detector plane.
    pitch = state.fov_mm / max(rows, cols)
    h_px = min(state.collimation_mm[0], state.fov_mm) / pitch
    v_px = min(state.collimation_mm[1], state.fov_mm) / pitch
    ds = Dataset()
    apply_common(ds, study)
    ds.ImageType = ["ORIGINAL", "PRIMARY", "SINGLE PLANE"]
    ds.SOPClassUID = XRayRadiofluoroscopicImageStorage
    ds.SOPInstanceUID = study.image_uid(state.save_count)
    # The series of saved images begins with the session, so every image of it has one series time.
    ds.SeriesDate, ds.SeriesTime = ds.StudyDate, ds.StudyTime
    ds.ContentDate = ds.AcquisitionDate = when.strftime("%Y%m%d")
    ds.ContentTime = ds.AcquisitionTime = when.strftime("%H%M%S.%f")
    ds.Modality = "RF"
    ds.SeriesDescription = f"Saved images, {study.case_title}"[:64]
    ds.OperatorsName = person_name(study.operator)
    ds.SeriesInstanceUID = study.image_series_uid
    ds.SeriesNumber = 1
    ds.InstanceNumber = state.save_count
    ds.PatientOrientation = ""
    ds.ImageLaterality = "U"      # the trunk: an unpaired body part
    ds.ReferencedPerformedProcedureStepSequence = procedure_step_reference(study)
    # The step as PS3.17 J.2.2 asks a modality without MPPS to describe it (see study.procedure_step_uid).
    ds.PerformedProcedureStepID = ds.StudyID
    ds.PerformedProcedureStepStartDate, ds.PerformedProcedureStepStartTime = ds.StudyDate, ds.StudyTime
    ds.PerformedProcedureStepDescription = f"Training session, {study.case_title}"[:64]
    if event_uid is not None:
        ds.IrradiationEventUID = event_uid
    ds.ImageComments = f"{'Held' if state.image == 'held' else 'Live'} image; fluoroscopy time {state.fluoro_time_display} min"
    # Exposure.
    ds.KVP = _ds_number(state.kvp)
    ds.RadiationSetting = "SC"       # low-dose fluoroscopic setting, not a radiographic acquisition
    ds.XRayTubeCurrent = int(round(state.ma))
    ds.XRayTubeCurrentInuA = _ds_number(state.ma * 1000.0)
    ds.RadiationMode = "PULSED" if state.pulse_rate_per_s else "CONTINUOUS"
    if state.pulse_rate_per_s:
        ds.AveragePulseWidth = _ds_number(fl.tube.pulse_width_ms)
        ds.ExposureTime = int(round(fl.tube.pulse_width_ms))   # ms: this image is one pulse
    else:
        ds.ExposureTime = None    # continuous: the frame's exposure is not a defined pulse (Type 2, empty)
    ds.FocalSpots = _ds_number(fl.tube.focal_spot_mm)
    # Geometry.
    ds.DistanceSourceToDetector = _ds_number(fl.geometry.source_to_image_mm)
    ds.DistanceSourceToPatient = _ds_number(fl.geometry.source_to_isocentre_mm)
    ds.EstimatedRadiographicMagnificationFactor = _ds_number(fl.geometry.source_to_image_mm / fl.geometry.source_to_isocentre_mm)
    if T_xray_from_ct is not None:
        # The C-arm's angulation as a C-arm's RF image carries it (the XA Positioner's attributes:
        # a Standard Extended RF image, as a mobile C-arm's are; the RF IOD has only Column Angulation).
        primary, secondary = positioner_angles(T_xray_from_ct)
        ds.PositionerPrimaryAngle = _ds_number(round(primary, 1))
        ds.PositionerSecondaryAngle = _ds_number(round(secondary, 1))
    ds.ImagerPixelSpacing = [_ds_number(pitch), _ds_number(pitch)]
    round_field = fl.detector.kind == "image_intensifier"
    ds.FieldOfViewShape = "ROUND" if round_field else "RECTANGLE"
    ds.FieldOfViewDimensions = [int(round(state.fov_mm))] if round_field else [int(round(state.fov_mm))] * 2
    if round_field:
        ds.IntensifierSize = _ds_number(fl.zoom_levels[0].fov_mm)
    ds.CollimatorShape = "RECTANGULAR"
    ds.CollimatorLeftVerticalEdge = int(round((cols - h_px) / 2))
    ds.CollimatorRightVerticalEdge = int(round((cols + h_px) / 2))
    ds.CollimatorUpperHorizontalEdge = int(round((rows - v_px) / 2))
    ds.CollimatorLowerHorizontalEdge = int(round((rows + v_px) / 2))
    # Dose so far in the session (dGy cm^2).
    ds.ImageAndFluoroscopyAreaDoseProduct = _ds_number(state.dap_gy_cm2 * 10.0)
    # Pixels.
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = "MONOCHROME2"
    ds.Rows, ds.Columns = rows, cols
    bits = 8 if pixels.dtype == np.uint8 else 16
    ds.BitsAllocated = ds.BitsStored = bits
    ds.HighBit = bits - 1
    ds.PixelRepresentation = 0
    ds.PixelIntensityRelationship = "DISP"
    # Stored as shown: an image saved while inverted holds the inverted pixels, so a viewer
    # must not invert again (IDENTITY), and the window spans the stored range unchanged.
    ds.PresentationLUTShape = "IDENTITY"
    ds.WindowCenter = _ds_number((2 ** bits - 1) / 2.0)
    ds.WindowWidth = _ds_number(2 ** bits)
    ds.LossyImageCompression = "00"
    ds.PixelData = np.ascontiguousarray(pixels).tobytes()
    return ds


def save_image(image: np.ndarray, state: ConsoleState, fluoroscope: FluoroscopeProfile, out_dir: Path, *,
               t_wall: float, study: SessionStudy, event_uid: str | None,
               T_xray_from_ct: np.ndarray | None = None) -> tuple[Path, Path]:
    """Write image-<session>-<n>.png and .dcm into `out_dir`; never overwrites. Returns both paths."""
    pixels = _as_display(image)
    out_dir = Path(out_dir)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise FluorosimError(f"{out_dir}: cannot create the saved-images folder ({e.strerror or e}); "
                             "check data_dir in the appliance profile") from None
    stem = f"image-{study.session_id:06d}-{state.save_count:04d}"
    ok, png = cv2.imencode(".png", pixels)
    if not ok:
        raise FluorosimError(f"{out_dir / stem}.png: the image could not be encoded as PNG")
    dicom = encode(dicom_image(pixels, state, fluoroscope, t_wall=t_wall, study=study, event_uid=event_uid,
                               T_xray_from_ct=T_xray_from_ct))
    png_path = write_atomic(out_dir / f"{stem}.png", png.tobytes(), overwrite=False)
    try:
        dcm_path = write_atomic(out_dir / f"{stem}.dcm", dicom, overwrite=False)
    except FluorosimError:
        png_path.unlink(missing_ok=True)
        raise
    return png_path, dcm_path
