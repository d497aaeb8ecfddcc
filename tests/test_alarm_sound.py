"""The audible 5-minute alarm repeats while it lasts and stops at reset (21 CFR 1020.32(h)(2))."""

from __future__ import annotations

import time
from pathlib import Path

from appliance.console.alarm_sound import AlarmSound, alarm_wav


def quick_player(tmp_path: Path) -> Path:
    """A stand-in `aplay` that takes one pattern, notes it, and exits at once, as a real player
    does at the end of its input: only then does the repeat path of the alarm run."""
    log = tmp_path / "played.log"
    player = tmp_path / "bin" / "aplay"
    player.parent.mkdir()
    player.write_text(f"#!/bin/sh\nbytes=$(wc -c)\necho \"$bytes\" >> {log}\n")
    player.chmod(0o755)
    return log


def patterns_played(log: Path) -> list[int]:
    return [int(line) for line in log.read_text().split()] if log.exists() else []


def wait_for(condition, timeout_s: float = 5.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.01)
    return condition()


def test_alarm_repeats_until_reset_then_stays_silent(tmp_path, monkeypatch):
    cards = tmp_path / "cards"
    cards.write_text(" 0 [PCH            ]: HDA-Intel - HDA Intel PCH\n")
    log = quick_player(tmp_path)
    monkeypatch.setenv("PATH", f"{log.parent / 'bin'}:/usr/bin:/bin")
    sound = AlarmSound(cards=cards)
    assert sound.available, sound.reason

    # The console calls update() every frame while the alarm sounds.
    def sounding_frames_until(n: int) -> bool:
        sound.update(True)
        return len(patterns_played(log)) >= n

    assert wait_for(lambda: sounding_frames_until(3)), f"the alarm played {len(patterns_played(log))} times, not 3"
    assert set(patterns_played(log)) == {len(alarm_wav())}, "each repeat is the whole pattern"

    sound.update(False)                               # reset by a person
    assert not sound.playing
    settled = len(patterns_played(log))
    for _ in range(50):
        sound.update(False)
        time.sleep(0.005)
    assert len(patterns_played(log)) == settled, "no beep after the reset"
