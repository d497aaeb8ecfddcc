"""What every DICOM object the appliance writes shares: UIDs, decimal strings, the simulated
patient, and the Part 10 encoding. The dose report (`rdsr`) and the saved images
(`saved_images`) both build on these.
"""

from __future__ import annotations

import io
import uuid

from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.uid import PYDICOM_IMPLEMENTATION_UID, ExplicitVRLittleEndian

from ..config.case import Patient

#: Name-based UUIDs (RFC 4122 version 5) in this namespace give the 2.25 UIDs of PS3.5 B.2.
_UID_NAMESPACE = uuid.UUID("6f1b9d3e-4a57-5c1e-9f0b-3c6d2a8e7b41")
#: A Decimal String (DS) holds at most this many characters (PS3.5 6.2).
DS_MAX_CHARS = 16


def uid(*parts: object) -> str:
    """A UID derived from ledger content: re-exporting a session gives the same UIDs."""
    return "2.25." + str(uuid.uuid5(_UID_NAMESPACE, "\x1f".join(str(p) for p in parts)).int)


def ds_number(value: float) -> str:
    """A Decimal String of at most 16 characters that keeps as many digits as fit."""
    for digits in range(12, 0, -1):
        text = f"{value:.{digits}g}"
        if len(text) <= DS_MAX_CHARS:
            return text
    return "0"


def set_simulated_patient(ds: Dataset, patient: dict | None, session_id: int) -> None:
    """The Patient module of a training session's objects: never a real person's name or ID, with
    the virtual patient's sex, age, weight and height as the session recorded them."""
    p = Patient(**{k: v for k, v in (patient or {}).items() if k in Patient.model_fields})
    ds.PatientName = "SIMULATED^TRAINING"
    ds.PatientID = f"SIM-{session_id}"
    ds.PatientBirthDate = ""
    ds.PatientSex = p.sex
    ds.PatientAge = f"{p.age_years:03d}Y"
    ds.PatientWeight = ds_number(p.weight_kg)
    ds.PatientSize = ds_number(p.height_m)


def encode(ds: Dataset) -> bytes:
    """The dataset as a DICOM Part 10 file."""
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = ds.SOPClassUID
    meta.MediaStorageSOPInstanceUID = ds.SOPInstanceUID
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    meta.ImplementationClassUID = PYDICOM_IMPLEMENTATION_UID
    ds.file_meta = meta
    buffer = io.BytesIO()
    ds.save_as(buffer, enforce_file_format=True)
    return buffer.getvalue()
