"""One run (an irradiation event): pedal-down to release, or to a change of exposure settings,
with its own time, dose and pulse count as the ledger records it in `fluoro_off`."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class Run:
    """The running account of one irradiation event (s, mGy, Gy cm^2)."""

    run: int                # 1, 2, ... this session
    reason_on: str
    start_t: float          # s, monotonic
    next_pulse_t: float     # s; pulsed modes only
    next_progress_t: float  # s; continuous modes only
    duration_s: float = 0.0
    air_kerma_mgy: float = 0.0
    dap_gy_cm2: float = 0.0
    pulses: int = 0
    # Time integrals of the technique the generator held (kV s, mA s), for the run's means.
    kvp_s: float = 0.0
    ma_s: float = 0.0

    def hold(self, dt_s: float, kvp: float, ma: float) -> None:
        """`dt_s` more seconds of exposure at `kvp` (kV) and `ma` (mA)."""
        self.duration_s += dt_s
        self.kvp_s += kvp * dt_s
        self.ma_s += ma * dt_s

    def mean_technique(self, kvp: float, ma: float) -> tuple[float, float]:
        """(kV, mA) averaged over the run's time, as the RDSR's per-event KVP and X-Ray Tube
        Current are (the mean over the irradiation event: the exposure control moves them
        during a run); `kvp` and `ma`, the technique now, for a run that lasted no time."""
        if self.duration_s <= 0:
            return kvp, ma
        return self.kvp_s / self.duration_s, self.ma_s / self.duration_s

    def technique_so_far(self) -> dict:
        """What each progress record and pulse records of the run's technique: its time integrals
        up to that instant (kV s, mA s), from which a run a crash cut off gets its means
        (recovered_technique)."""
        return {"kvp_s": self.kvp_s, "ma_s": self.ma_s}

    def schedule_next_pulse(self, rate_per_s: float) -> None:
        """The next pulse after `pulses` of them, counted from the run's start rather than the
        last pulse, so summed periods do not drift."""
        self.next_pulse_t = self.start_t + self.pulses / rate_per_s

    def summary(self) -> dict:
        """What `fluoro_off` records of the run (s, mGy, Gy cm^2)."""
        return {"start_t": self.start_t, "duration_s": self.duration_s, "air_kerma_mgy": self.air_kerma_mgy,
                "dap_gy_cm2": self.dap_gy_cm2, "pulses": self.pulses}


def recovered_technique(started: dict, events: list[dict]) -> dict:
    """The kV and mA of a run a crash cut off, from its committed events (ledger rows: kind,
    d_fluoro_time_s, detail as a dict) after its `fluoro_on` (`started`, the technique it began
    with): the time-weighted means up to its last progress record or pulse, as fluoro_off would
    have recorded them; the technique it began with if none was committed."""
    elapsed, means = 0.0, {"kvp": started.get("kvp"), "ma": started.get("ma")}
    for e in events:
        elapsed += e["d_fluoro_time_s"]
        if "kvp_s" in e["detail"] and elapsed > 0:
            means = {"kvp": e["detail"]["kvp_s"] / elapsed, "ma": e["detail"]["ma_s"] / elapsed}
    return means
