"""Which console action a key, HID usage or pedal stands for, through the keymap profile."""

from __future__ import annotations

import typing

from ..config.keymap import Action, KeymapProfile

#: Every action the console knows, as the keymap spells them.
ACTIONS: frozenset[str] = frozenset(typing.get_args(Action))


def action_for(keymap: KeymapProfile, key: str) -> str | None:
    """The action of `key`: "pedal" is fluoroscopy, "hid:0x58" goes through hid_usages, an
    evdev name through keys, and an action name (scripted input) stands for itself."""
    if key == "pedal":
        return "fluoro"
    if key.startswith("hid:"):
        try:
            return keymap.hid_usages.get(int(key[4:], 16))
        except ValueError:
            return None
    if key in keymap.keys:
        return keymap.keys[key]
    if key in ACTIONS:
        return key
    return None


def typed_by_badge_reader(name: str) -> bool:
    """Whether `name` is a key a keyboard-like badge or barcode reader types into the trainee's
    name (letters, digits, shift, enter): meaningful in a scripted session though not in the keymap."""
    from ..teaching.live import BADGE_KEYS

    return name in BADGE_KEYS
