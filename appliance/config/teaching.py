"""The appliance profile's `teaching` section: which exercise it offers and how it is recorded."""

from __future__ import annotations

from pydantic import Field

from .base import Section


class Teaching(Section):
    exercise: str | None = Field(None, description="Exercise offered on this appliance (configs/exercises/*.yaml), "
                                                   "relative to this file; omit for none.")
    shot_counter: bool = Field(True, description="Show the number of exposures (pedal presses) of the session on screen.")
    view_period_s: float = Field(0.2, gt=0, le=10, description="While exposing, at most one image-geometry (view) record "
                                 "per this much console time; the first image of each exposure and every saved image "
                                 "are always recorded (s).")
    cue_s: float = Field(3.0, gt=0, le=60, description="How long the verdict after a save stays on screen (s, console clock).")
    trainees: list[str] = Field(default_factory=list, description="Roster the keymap's trainee_next key steps through; "
                                "a badge or barcode reader that types like a keyboard needs none.")
