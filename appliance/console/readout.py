"""What the console tells the rest of the appliance: the events the ledger records and the
state the display shows and the renderer needs.

`appliance/console/state.py` is the state machine that produces both.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

#: The fluoroscopy time display counts tenths of a minute (s).
SECONDS_PER_TENTH_MINUTE = 6.0


@dataclass(frozen=True)
class ConsoleEvent:
    """Something the ledger records. Totals are cumulative after the event; d_* are the
    increments since the previous event (s, mGy, Gy cm^2)."""

    t_monotonic: float
    kind: str
    detail: dict = field(default_factory=dict)
    fluoro_time_s: float = 0.0
    air_kerma_mgy: float = 0.0
    dap_gy_cm2: float = 0.0
    d_fluoro_time_s: float = 0.0
    d_air_kerma_mgy: float = 0.0
    d_dap_gy_cm2: float = 0.0


#: Kinds of ConsoleEvent, for readers of the ledger.
EVENT_KINDS = ("fluoro_on", "fluoro_off", "pulse", "exposure", "zoom", "collimation", "mode", "invert", "save",
               "hold_breath", "resume_breath", "alarm", "alarm_reset", "profile", "breath_rate", "breath_depth")


@dataclass(frozen=True)
class ConsoleState:
    """What the display shows and the renderer needs, at time `t` (s)."""

    t: float
    fluoro_on: bool
    image: str                      # "live", "held" (last-image-hold) or "none" (nothing exposed yet)
    mode: str
    pulse_rate_per_s: float | None  # None: continuous
    zoom: int                       # 1 (widest) .. 4
    fov_mm: float
    collimation_mm: tuple[float, float]  # (horizontal, vertical) blade openings at the detector plane
    invert: bool
    breath_hold: bool
    fluoro_time_s: float
    fluoro_time_display: str        # minutes and tenths, e.g. "5.3"
    air_kerma_mgy: float
    dap_gy_cm2: float
    air_kerma_rate_mgy_per_min: float  # now (0 when not exposing)
    alarm_sounding: bool
    alarm_count: int
    save_count: int
    runs: int
    kvp: float
    ma: float
    pulses: int = 0                 # pulses so far this session (counts images in the pulsed modes)
    window_scale: float = 1.0       # the radiographer's window: the automatic width times this
    level_shift: float = 0.0        # the radiographer's level: the centre moved by this fraction of the width
    breath_rate_steps: int = 0      # faster minus slower presses so far (the breathing model applies each step)
    breath_depth_steps: int = 0     # deeper minus shallower presses so far
    breath_changed_t: float = 0.0   # console time of the last breath hold or resume press (s): the breathing model stops there
    breath_step_t: float = 0.0      # console time of the last faster/slower/deeper/shallower press (s): the model changes there

    @property
    def held(self) -> bool:
        return self.image == "held"

    @property
    def collimated_mm(self) -> tuple[float, float] | None:
        """The blade opening (horizontal, vertical mm at the detector plane) when the blades cut
        into the field of view; None when they are fully open."""
        c, fov = self.collimation_mm, self.fov_mm
        return None if c[0] >= fov and c[1] >= fov else (c[0], c[1])

    def image_due(self, drawn: ConsoleState | None) -> bool:
        """Whether a new image is due, `drawn` being the state the image on screen was rendered at.

        Continuous fluoroscopy shows a new image whenever one can be made; a pulsed mode only
        one per pulse, as on the real unit. This holds across states a slower reader never
        saw: a pulse since `drawn` is a pulse not drawn.
        """
        if not self.fluoro_on:
            return False
        if self.pulse_rate_per_s is None:
            return True
        return drawn is None or self.pulses > drawn.pulses


def minutes_and_tenths(seconds: float) -> str:
    """Fluoroscopy time as a clinical display shows it: whole tenths of a minute, never rounded up."""
    tenths = int(math.floor(max(seconds, 0.0) / SECONDS_PER_TENTH_MINUTE + 1e-9))
    return f"{tenths // 10}.{tenths % 10}"
