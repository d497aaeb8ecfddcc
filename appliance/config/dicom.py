"""The appliance's `dicom:` section: who the appliance is on the hospital network, and where
its images and dose reports go.

Identity (institution, department, station name, serial number) is written into every image
and dose report; the Device Observer UID, which a dose registry uses to tell one X-ray unit
from another, is not configured but generated once per appliance (see records.identity) and
kept in `identity_file`.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field, field_validator, model_validator

from .base import Section

# PS3.5 6.2: an AE title is 1-16 characters of the default repertoire, no backslash or
# control characters; leading and trailing spaces are not significant.
_AE_TITLE = r"^[ -\[\]-~]{1,16}$"


def _ae_title(value: str) -> str:
    if not value.strip():
        raise ValueError("an AE title may not be blank")
    return value.strip()


class Tls(Section):
    """TLS for one destination (DICOM over TLS, PS3.15 B.1): paths relative to the profile."""

    ca_file: str = Field(description="PEM file of the certificate authorities that sign the destination's certificate.")
    cert_file: str | None = Field(None, description="PEM certificate this appliance presents, when the destination asks for one.")
    key_file: str | None = Field(None, description="PEM private key of cert_file.")
    server_name: str | None = Field(None, description="Name to check the destination's certificate against; default: host.")

    @model_validator(mode="after")
    def _pair(self) -> Tls:
        if (self.cert_file is None) != (self.key_file is None):
            raise ValueError("give cert_file and key_file together, or neither")
        return self


class Destination(Section):
    name: str = Field(min_length=1, max_length=32, pattern=r"^[A-Za-z0-9_.-]+$",
                      description="Short name used in commands, logs and the banner (letters, digits, - _ .).")
    ae_title: str = Field(pattern=_AE_TITLE, description="The destination's (called) AE title.")
    host: str = Field(min_length=1, description="Host name or IP address of the destination.")
    port: int = Field(gt=0, lt=65536, description="TCP port of the destination's DICOM service.")
    objects: Literal["images", "dose_reports", "both"] = Field(
        "both", description="What it takes: saved images (PACS), dose reports (dose registry), or both.")
    tls: Tls | None = Field(None, description="DICOM over TLS; omit for plain TCP.")

    _strip = field_validator("ae_title")(_ae_title)

    def takes(self, what: Literal["image", "dose_report"]) -> bool:
        return self.objects == "both" or self.objects == ("images" if what == "image" else "dose_reports")

    def label(self) -> str:
        return f"'{self.name}' ({self.ae_title}@{self.host}:{self.port})"


class Retry(Section):
    """How a destination that does not answer is tried again; the queue keeps everything meanwhile."""

    first_delay_s: float = Field(10.0, gt=0, le=3600, description="Wait after the first failed attempt (s); doubled "
                                                                  "after each further failure.")
    max_delay_s: float = Field(900.0, gt=0, le=86400, description="Longest wait between two attempts (s).")
    warn_after_failures: int = Field(3, ge=1, le=1000, description="Consecutive failed attempts after which a destination "
                                     "counts as failing: banner on screen and a log line (attempts).")
    poll_period_s: float = Field(2.0, gt=0, le=600, description="How often the running appliance looks for due objects (s).")


class Dicom(Section):
    ae_title: str = Field("FLUOROSIM", pattern=_AE_TITLE, description="This appliance's (calling) AE title.")
    institution: str = Field("fluorosim training appliance", min_length=1, max_length=64,
                             description="Institution Name written into images and dose reports.")
    department: str | None = Field(None, min_length=1, max_length=64, description="Institutional Department Name; omit if none.")
    station_name: str = Field("FLUOROSIM", min_length=1, max_length=16, description="Station Name (at most 16 characters).")
    serial_number: str = Field("unset", min_length=1, max_length=64, description="Device Serial Number of this appliance "
                               "(the label on the box); dose registries show it with the device.")
    patient_id_issuer: str = Field("FLUOROSIM", min_length=1, max_length=64, description="Issuer of Patient ID: the virtual "
                                   "patients' IDs are unique per appliance, so the issuer is qualified by the Device Observer UID.")
    identity_file: str | None = Field(None, description="File holding this appliance's Device Observer UID, generated "
                                      "once (`fluorosim dicom identity`); relative to this profile unless absolute; "
                                      "default: device-identity in data_dir.")
    timeout_s: float = Field(10.0, gt=0, le=300, description="Connection, association and response time-out for one destination (s).")
    send_at_shutdown_s: float = Field(0.5, ge=0, le=1, description="When the session ends at shutdown, how long its dose "
                                      "report may take to send at once, over all destinations (s); what does not go "
                                      "in time stays queued for the next start. 0: always leave it queued. The service "
                                      "has 2 s to stop in all.")
    retry: Retry = Field(default_factory=Retry, description="Retry and warning policy of the send queue.")
    destinations: list[Destination] = Field(default_factory=list, description="Where images and dose reports are sent; empty: nowhere.")

    _strip = field_validator("ae_title")(_ae_title)

    @field_validator("destinations")
    @classmethod
    def _unique_names(cls, destinations: list[Destination]) -> list[Destination]:
        names = [d.name for d in destinations]
        for name in names:
            if names.count(name) > 1:
                raise ValueError(f"destination name '{name}' is used twice; names must be unique")
        return destinations

    def destination(self, name: str) -> Destination | None:
        return next((d for d in self.destinations if d.name == name), None)
