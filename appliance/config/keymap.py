"""Which key or pedal does what on the console."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from .base import Findings, Section

Action = Literal[
    "fluoro",
    "collimate_h_open", "collimate_h_close", "collimate_v_open", "collimate_v_close",
    "zoom_1", "zoom_2", "zoom_3", "zoom_4", "zoom_next", "zoom_prev",
    "mode_next", "save", "invert", "alarm_reset", "hold_breath", "resume_breath",
]


class KeymapProfile(Section):
    name: str = Field(min_length=1, description="The keypad this map is for.")
    keys: dict[str, Action] = Field(default_factory=dict, description="evdev key names (KEY_*, BTN_*) to actions.")
    hid_usages: dict[int, Action] = Field(default_factory=dict, description="HID keyboard-page usage ids (integers) "
                                                                            "to actions, for hidapi keypads.")

    def problems(self) -> Findings:
        for name in self.keys:
            if not (name.startswith("KEY_") or name.startswith("BTN_")) or not name.replace("_", "").isalnum():
                yield ("keys", name), "must be an evdev key name such as KEY_F1 or BTN_0"
        if not self.keys and not self.hid_usages:
            yield ("keys",), "map at least one key or HID usage"
