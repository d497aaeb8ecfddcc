"""Who this appliance is on the DICOM network: its Device Observer UID and its equipment record.

A dose registry tells X-ray units apart by their Device Observer UID, so every appliance needs
its own, made once and kept for the life of the box: `fluorosim dicom identity` (run by
provisioning) generates a 2.25 UUID-derived UID into the profile's `dicom.identity_file`
(/etc/fluorosim/device-identity on an appliance; data_dir/device-identity in a checkout)
and never changes an existing one. Each session records the identity it ran with, so a dose
report rebuilt later from the ledger names the same device.
"""

from __future__ import annotations

import re
import uuid
from pathlib import Path

from ..atomic_file import write_atomic
from ..config.dicom import Dicom
from ..config.fluoroscope import FluoroscopeProfile
from ..errors import FluorosimError

_UID = re.compile(r"^(0|[1-9][0-9]*)(\.(0|[1-9][0-9]*))+$")


def identity_path(config_path: Path, data_dir: Path, dicom: Dicom) -> Path:
    """Where the appliance's Device Observer UID is kept."""
    if dicom.identity_file is None:
        return data_dir / "device-identity"
    written = Path(dicom.identity_file)
    return written if written.is_absolute() else config_path.parent / written


def read_device_uid(path: Path) -> str | None:
    """The UID kept in `path`, None if the file does not exist; a damaged file is an error."""
    try:
        text = path.read_text(encoding="ascii").strip()
    except FileNotFoundError:
        return None
    except (OSError, UnicodeDecodeError) as e:
        raise FluorosimError(f"{path}: cannot read the appliance's Device Observer UID ({e}); "
                             "restore the file from a backup (a new UID makes this a different device to the dose registry)") from None
    if not _UID.match(text) or len(text) > 64:
        raise FluorosimError(f"{path}: '{text[:70]}' is not a DICOM UID; restore the file from a backup, or delete it and run "
                             "'fluorosim dicom identity' (the registry will then see a new device)")
    return text


def device_uid(path: Path, *, create: bool = True) -> str:
    """This appliance's Device Observer UID, generated into `path` the first time if `create`."""
    existing = read_device_uid(path)
    if existing is not None:
        return existing
    if not create:
        raise FluorosimError(f"{path}: no Device Observer UID yet; run 'fluorosim dicom identity' once (provisioning does)")
    uid = f"2.25.{uuid.uuid4().int}"
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        write_atomic(path, (uid + "\n").encode("ascii"), overwrite=False)
    except OSError as e:
        raise FluorosimError(f"{path}: cannot store the new Device Observer UID ({e.strerror or e}); "
                             "run 'fluorosim dicom identity' as the provisioning user") from None
    return uid


def equipment_of(fluoroscope: FluoroscopeProfile, dicom: Dicom, uid: str) -> dict:
    """What a session records about its machine and appliance, for images and dose reports
    (`uid` empty when the appliance has none: the objects then fall back to a profile-derived one)."""
    return {"manufacturer": fluoroscope.manufacturer, "model": fluoroscope.model, "serial": dicom.serial_number,
            "device_uid": uid or None, "institution": dicom.institution, "department": dicom.department,
            "station_name": dicom.station_name, "patient_id_issuer": dicom.patient_id_issuer}
