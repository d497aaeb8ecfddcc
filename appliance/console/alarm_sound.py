"""The audible fluoroscopy-time alarm, played through ALSA when the machine has a sound card.

21 CFR 1020.32(h)(2) asks for an audible signal at each 5 minutes of fluoroscopy that lasts
until reset. The console decides when the alarm sounds; this plays it: a beeping tone piped
to ALSA's `aplay`, restarted while the alarm lasts and stopped at reset. Without a sound card
(no /proc/asound/cards entry) or without `aplay` the alarm is visual only, and `reason` says
why so the display can show it.
"""

from __future__ import annotations

import io
import shutil
import subprocess
import wave
from pathlib import Path

import numpy as np

#: Beep pitch (Hz), length and gap (s), and loudness (fraction of full scale) of one pattern.
TONE_HZ = 880.0
BEEP_S = 0.4
GAP_S = 0.4
BEEPS_PER_PATTERN = 3
LEVEL = 0.5
SAMPLE_RATE_HZ = 16000


def alarm_wav(tone_hz: float = TONE_HZ, beep_s: float = BEEP_S, gap_s: float = GAP_S, beeps: int = BEEPS_PER_PATTERN,
              level: float = LEVEL, rate_hz: int = SAMPLE_RATE_HZ) -> bytes:
    """One pattern of beeps as a mono 16-bit WAV file."""
    t = np.arange(int(round(beep_s * rate_hz))) / rate_hz
    beep = np.sin(2 * np.pi * tone_hz * t)
    ramp = min(len(t) // 10, int(0.01 * rate_hz))      # 10 ms fades: no clicks
    if ramp:
        fade = np.linspace(0.0, 1.0, ramp)
        beep[:ramp] *= fade
        beep[-ramp:] *= fade[::-1]
    gap = np.zeros(int(round(gap_s * rate_hz)))
    pattern = np.concatenate([np.concatenate([beep, gap]) for _ in range(beeps)])
    samples = np.round(pattern * level * 32767).astype("<i2")
    buffer = io.BytesIO()
    with wave.open(buffer, "wb") as w:
        w.setnchannels(1)
        w.setsampwidth(2)
        w.setframerate(rate_hz)
        w.writeframes(samples.tobytes())
    return buffer.getvalue()


class AlarmSound:
    """Call `update(sounding)` every frame; it starts, repeats and stops the sound as needed."""

    def __init__(self, cards: str | Path = "/proc/asound/cards", player: str = "aplay"):
        self.player = shutil.which(player)
        cards = Path(cards)
        has_card = cards.is_file() and "no soundcards" not in cards.read_text(errors="replace") and cards.read_text().strip()
        if not has_card:
            self.reason = "no sound card (ALSA lists none); the alarm is visual only"
        elif self.player is None:
            self.reason = f"{player} (Debian package alsa-utils) not found; the alarm is visual only"
        else:
            self.reason = ""
        self.available = not self.reason
        self._wav = alarm_wav()
        self._process: subprocess.Popen | None = None

    @property
    def playing(self) -> bool:
        return self._process is not None and self._process.poll() is None

    def update(self, sounding: bool) -> None:
        if not self.available:
            return
        if sounding and not self.playing:
            self._start()
        elif not sounding and self._process is not None:
            self.stop()

    def _start(self) -> None:
        if self.player is None:     # `available` is false then; update() never gets here
            return
        try:
            process = subprocess.Popen([self.player, "-q", "-t", "wav", "-"], stdin=subprocess.PIPE,
                                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            self._process = process
            if process.stdin is not None:   # always set with stdin=PIPE
                process.stdin.write(self._wav)
                process.stdin.close()
        except OSError as e:
            self.available = False
            self.reason = f"cannot play the alarm ({e.strerror or e}); the alarm is visual only"
            self._process = None

    def stop(self) -> None:
        if self._process is not None:
            if self._process.poll() is None:
                self._process.terminate()
                try:
                    self._process.wait(timeout=1.0)
                except subprocess.TimeoutExpired:
                    self._process.kill()
                    self._process.wait()
            self._process = None
