"""The appliance profile's `teaching` section: which exercise it offers and how it is recorded."""

from __future__ import annotations

from urllib.parse import urlsplit

from pydantic import Field, field_validator

from .base import Section
from .dicom import Retry


def _url(value: str) -> str:
    parts = urlsplit(value)
    if parts.scheme not in ("http", "https") or not parts.hostname:
        raise ValueError("must be an http:// or https:// URL with a host")
    return value


class Lrs(Section):
    """A Learning Record Store that takes each ended session's results as xAPI statements."""

    endpoint: str = Field(description="The LRS's xAPI endpoint, e.g. https://lrs.sim-centre.org/xAPI/ (statements go "
                                      "to <endpoint>/statements).")
    username: str = Field(min_length=1, description="HTTP basic-auth user the LRS gave this appliance.")
    password_file: str = Field(min_length=1, description="File holding that user's password (one line), relative to this "
                                                         "profile unless absolute; kept out of the profile itself.")
    account_home_page: str = Field(description="Home page of the system whose accounts the trainee names are "
                                               "(the xAPI actor's account.homePage), e.g. the centre's booking system.")
    appliance_id: str = Field("fluorosim", min_length=1, description="Names this appliance in each statement's context.")
    timeout_s: float = Field(10.0, gt=0, le=120, description="How long one request to the LRS may take (s).")
    send_at_shutdown_s: float = Field(0.5, ge=0, le=1, description="When the session ends at shutdown, how long its "
                                      "statements may take to send at once (s); what does not go in time stays queued "
                                      "for the running appliance's next start. 0: always leave them queued.")
    retry: Retry = Field(default_factory=Retry, description="Retry and warning policy for the LRS, as for a DICOM "
                                                            "destination: the statements wait in the ledger's send queue.")

    _check_endpoint = field_validator("endpoint", "account_home_page")(lambda cls, v: _url(v))


class Teaching(Section):
    exercise: str | None = Field(None, description="Exercise offered on this appliance (configs/exercises/*.yaml), "
                                                   "relative to this file; omit for none.")
    shot_counter: bool = Field(True, description="Show the number of exposures (pedal presses) of the session on screen.")
    view_period_s: float = Field(0.2, gt=0, le=10, description="While exposing, at most one image-geometry (view) record "
                                 "per this much console time; the first image of each exposure and every saved image "
                                 "are always recorded (s).")
    cue_s: float = Field(3.0, gt=0, le=60, description="How long the verdict after a save stays on screen (s, wall clock).")
    badge_reader: str | None = Field(None, description="A badge or barcode reader that types like a keyboard: its evdev "
                                     "device (path, udev symlink, 'name:TEXT' or 'VVVV:PPPP'); what it types, ended by "
                                     "Enter, is the trainee's name, and none of its keys reaches the console; omit for none.")
    lrs: Lrs | None = Field(None, description="Send each ended session's results to this LRS; omit for none.")
    trainees: list[str] = Field(default_factory=list, description="Roster the keymap's trainee_next key steps through; "
                                "a badge or barcode reader that types like a keyboard needs none.")
