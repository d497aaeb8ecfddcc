"""The fluoroscope console as a pure state machine: no I/O, the clock is passed in.

Rules it keeps (a clinical unit's, and 21 CFR 1020.32's):
- Fluoroscopy is on only while the pedal or the fluoro key is held (any of them); on
  release the last image stays on screen, marked as held (last-image-hold).
- Continuous modes expose all the time; pulsed modes expose `pulse_rate_per_s` pulses per
  second, the first at pedal-down. The display renders a new image only on a pulse.
- Fluoroscopy time is pedal-down time; shown in minutes and tenths (so it changes every
  6 s of exposure). Each time it crosses a multiple of the profile's alarm period (300 s)
  the alarm sounds, and keeps sounding until the reset key.
- Collimation opens and closes in steps on each axis, between the profile's minimum and
  the field of view; it may be changed while the image is held (electronic collimation).
- Four zoom levels; invert; save; breath hold and resume.

Every change is returned as `ConsoleEvent`s carrying the running totals and their
increments since the previous event, so the ledger's sum of increments is the total. A run
(an irradiation event) ends with `fluoro_off` whose detail summarises it; changing zoom,
mode or collimation while exposing ends the run and starts a new one at the same instant,
so each run has one set of exposure settings.
"""

from __future__ import annotations

import math

from drivers.input_event import InputEvent

from ..config.fluoroscope import FluoroscopeProfile
from ..config.keymap import KeymapProfile
from . import dose
from .keys import action_for
from .readout import ConsoleEvent, ConsoleState, minutes_and_tenths
from .run import Run

#: While continuous fluoroscopy runs, an `exposure` event is recorded this often (s), so a
#: power cut loses at most this much of the record. Pulsed modes record every pulse.
PROGRESS_PERIOD_S = 1.0
#: Summed time steps may miss an alarm threshold by rounding; this much counts as reached (s).
ALARM_SLACK_S = 1e-9


class Console:
    def __init__(self, fluoroscope: FluoroscopeProfile, keymap: KeymapProfile, t0: float,
                 progress_period_s: float = PROGRESS_PERIOD_S):
        self.fl = fluoroscope
        self.keymap = keymap
        self.progress_period_s = progress_period_s
        self._t = t0
        self.zoom = 1
        self.mode_index = 0
        fov = fluoroscope.zoom_levels[0].fov_mm
        self.collimation: tuple[float, float] = (fov, fov)
        self.invert = fluoroscope.display.invert
        self.window_scale, self.level_shift = 1.0, 0.0
        self.breath_hold = False
        self.breath_changed_t = self.breath_step_t = 0.0
        self.breath_rate_steps = self.breath_depth_steps = 0
        self._fluoro_holders: set[tuple[str, str]] = set()
        self.fluoro_on = False
        self.has_image = False
        # Totals, and their values at the last event emitted (for the increments).
        self.fluoro_time_s = 0.0
        self.air_kerma_mgy = 0.0
        self.dap_gy_cm2 = 0.0
        self._recorded = (0.0, 0.0, 0.0)
        self.alarm_sounding = False
        self.alarm_count = 0
        self._next_alarm_s = fluoroscope.dose.alarm_period_s
        # Cumulative time and alarms carried from a session a crash ended (see carry_over).
        self.carried_fluoro_time_s = 0.0
        self.carried_alarms = 0
        # Tube output relative to the reference technique, as automatic brightness control set
        # it for the latest image (1 without it): the dose rate is the reference rate times this.
        self.exposure_factor = 1.0
        # The tube voltage and current it set (kV, mA): the reference technique's until it says.
        self.kvp, self.ma = fluoroscope.tube.kvp, fluoroscope.tube.ma
        self.save_count = 0
        self.runs = 0
        self._pulse_count = 0
        self._run: Run | None = None

    # --- settings -----------------------------------------------------------------
    @property
    def mode(self):
        return self.fl.tube.modes[self.mode_index]

    def _rate(self) -> float:
        return dose.air_kerma_rate_mgy_per_min(self.fl, self.zoom, self.mode.name) * self.exposure_factor

    def _area_cm2(self) -> float:
        return dose.field_area_reference_cm2(self.fl, self.zoom, self.collimation)

    # --- events -------------------------------------------------------------------
    def _emit(self, out: list, t: float, kind: str, **detail) -> None:
        ft, k, d = self.fluoro_time_s, self.air_kerma_mgy, self.dap_gy_cm2
        rft, rk, rd = self._recorded
        out.append(ConsoleEvent(t, kind, detail, ft, k, d, ft - rft, k - rk, d - rd))
        self._recorded = (ft, k, d)

    # --- time ---------------------------------------------------------------------
    def _accrue(self, t: float) -> None:
        """Advance totals to `t` with no discrete event in between."""
        dt = t - self._t
        if dt <= 0:
            return
        if self._run is not None:
            self.fluoro_time_s += dt
            self._run.hold(dt, self.kvp, self.ma)
            if self.mode.pulse_rate_per_s is None:
                kerma = self._rate() / 60.0 * dt
                self._add_kerma(kerma)
        self._t = t

    def _add_kerma(self, kerma: float) -> None:
        dap = dose.dap_gy_cm2(kerma, self._area_cm2())
        self.air_kerma_mgy += kerma
        self.dap_gy_cm2 += dap
        if self._run is not None:
            self._run.air_kerma_mgy += kerma
            self._run.dap_gy_cm2 += dap

    def _pulse(self, out: list, t: float, run: Run, rate: float) -> None:
        self._add_kerma(dose.kerma_per_pulse_mgy(self._rate(), rate))
        run.pulses += 1
        self._pulse_count += 1
        self.has_image = True
        self._emit(out, t, "pulse", run=run.run, n=run.pulses, **run.technique_so_far())
        run.schedule_next_pulse(rate)

    def _advance(self, t: float, out: list) -> None:
        """Advance to `t`, emitting every pulse, progress record and alarm due on the way."""
        if t <= self._t:
            return
        while self._run is not None:
            run = self._run
            rate = self.mode.pulse_rate_per_s
            # A pulse or progress record due exactly at `t` waits for the next advance (a release
            # at `t` comes first: pulses fall in [start, end)); the alarm is due at `t` itself,
            # with a nanosecond's slack for the rounding of summed time steps.
            due = []
            if rate is not None:
                due.append((run.next_pulse_t, 0, run.next_pulse_t < t))
            else:
                due.append((run.next_progress_t, 1, run.next_progress_t < t))
            alarm_t = self._t + (self._next_alarm_s - self.fluoro_time_s)
            due.append((alarm_t, 2, alarm_t <= t + ALARM_SLACK_S))
            due = [d for d in due if d[2]]
            if not due:
                break
            tn, what, _ = min(due)
            self._accrue(min(max(tn, self._t), t))
            if what == 0 and rate is not None:
                self._pulse(out, tn, run, rate)
            elif what == 1:
                self._emit(out, tn, "exposure", run=run.run, **run.technique_so_far())
                run.next_progress_t += self.progress_period_s
            else:
                # Land exactly on the threshold: 21 CFR counts the alarm at 5:00, not a float near it.
                self.fluoro_time_s = self._next_alarm_s
                self.alarm_sounding = True
                self.alarm_count += 1
                self._emit(out, tn, "alarm", n=self.alarm_count, at_fluoro_time_s=self._next_alarm_s)
                self._next_alarm_s += self.fl.dose.alarm_period_s
        self._accrue(t)

    # --- runs ---------------------------------------------------------------------
    def _start_run(self, out: list, t: float, reason: str) -> None:
        self.runs += 1
        self.fluoro_on = True
        rate = self.mode.pulse_rate_per_s
        run = Run(self.runs, reason, start_t=t, next_pulse_t=t, next_progress_t=t + self.progress_period_s)
        self._run = run
        self._emit(out, t, "fluoro_on", run=self.runs, reason=reason, **self._settings())
        if rate is None:
            self.has_image = True
        else:
            self._pulse(out, t, run, rate)

    def _end_run(self, out: list, t: float, reason: str) -> None:
        run = self._run
        self.fluoro_on = False
        if run is None:     # callers end a run only while exposing
            return
        # The kV and mA of a run are its time-weighted means; fluoro_on holds those it began with.
        kvp, ma = run.mean_technique(self.kvp, self.ma)
        self._emit(out, t, "fluoro_off", run=run.run, reason=reason, **run.summary(),
                   **{**self._settings(), "kvp": kvp, "ma": ma})
        self._run = None

    def _settings(self) -> dict:
        """The exposure settings of a run, as recorded with it (mm, kV, mA, ms, 1/s, cm^2, mGy/min)."""
        fl, mode = self.fl, self.mode
        h, v = self.collimation
        return {"mode": mode.name, "pulse_rate_per_s": mode.pulse_rate_per_s,
                "pulse_width_ms": fl.tube.pulse_width_ms if mode.pulse_rate_per_s else None,
                "kvp": self.kvp, "ma": self.ma, "focal_spot_mm": fl.tube.focal_spot_mm, "zoom": self.zoom,
                "fov_mm": fl.zoom_levels[self.zoom - 1].fov_mm, "collimation_h_mm": h, "collimation_v_mm": v,
                "field_area_cm2": self._area_cm2(), "air_kerma_rate_mgy_per_min": self._rate(),
                "sid_mm": fl.geometry.source_to_image_mm, "source_to_isocentre_mm": fl.geometry.source_to_isocentre_mm,
                "source_to_reference_mm": dose.reference_distance_mm(fl)}

    def _change_settings(self, out: list, t: float, apply, kind: str, detail) -> None:
        """Change exposure settings; while exposing, the current run ends and a new one starts."""
        exposing = self.fluoro_on
        if exposing:
            self._end_run(out, t, "settings changed")
        apply()
        self._emit(out, t, kind, **detail())
        if exposing:
            self._start_run(out, t, "settings changed")

    # --- input --------------------------------------------------------------------
    def handle(self, event: InputEvent) -> list[ConsoleEvent]:
        """Apply one key or pedal transition at its own time (never earlier than the last one seen)."""
        out: list[ConsoleEvent] = []
        t = max(event.t_monotonic, self._t)
        action = action_for(self.keymap, event.key)
        if action is None:
            return out
        self._advance(t, out)
        holder = (event.source, event.key)
        if action == "fluoro":
            if event.pressed:
                self._fluoro_holders.add(holder)
                if not self.fluoro_on:
                    self._start_run(out, t, "pressed")
            else:
                self._fluoro_holders.discard(holder)
                if self.fluoro_on and not self._fluoro_holders:
                    self._end_run(out, t, "released")
            return out
        if not event.pressed:
            return out
        fl = self.fl
        if action.startswith("zoom_"):
            target = {"zoom_next": min(self.zoom + 1, 4), "zoom_prev": max(self.zoom - 1, 1)}.get(action)
            target = target or int(action[5:])
            if target != self.zoom:
                self._change_settings(out, t, lambda: self._set_zoom(target), "zoom",
                                      lambda: {"zoom": self.zoom, "fov_mm": fl.zoom_levels[self.zoom - 1].fov_mm,
                                               "collimation_h_mm": self.collimation[0],
                                               "collimation_v_mm": self.collimation[1]})
        elif action.startswith("collimate_"):
            axis = 0 if action.startswith("collimate_h") else 1
            step = fl.collimator.step_mm if action.endswith("open") else -fl.collimator.step_mm
            fov = fl.zoom_levels[self.zoom - 1].fov_mm
            new = min(max(self.collimation[axis] + step, fl.collimator.min_opening_mm), fov)
            if new != self.collimation[axis]:
                opening = (new, self.collimation[1]) if axis == 0 else (self.collimation[0], new)
                self._change_settings(out, t, lambda: setattr(self, "collimation", opening), "collimation",
                                      lambda: {"collimation_h_mm": self.collimation[0],
                                               "collimation_v_mm": self.collimation[1]})
        elif action == "mode_next":
            if len(fl.tube.modes) > 1:
                nxt = (self.mode_index + 1) % len(fl.tube.modes)
                self._change_settings(out, t, lambda: setattr(self, "mode_index", nxt), "mode",
                                      lambda: {"mode": self.mode.name, "pulse_rate_per_s": self.mode.pulse_rate_per_s})
        elif action == "invert":
            self.invert = not self.invert
            self._emit(out, t, "invert", invert=self.invert)
        elif action in ("window_wider", "window_narrower", "level_up", "level_down", "window_reset"):
            self._adjust_window(action)
        elif action == "save":
            if self.has_image:
                self.save_count += 1
                self._emit(out, t, "save", n=self.save_count, image="live" if self.fluoro_on else "held")
        elif action == "alarm_reset":
            if self.alarm_sounding:
                self.alarm_sounding = False
                self._emit(out, t, "alarm_reset")
            elif self.carried_fluoro_time_s or self.carried_alarms:
                # With no alarm sounding, the press resets the timer carried over a crash: a person's act.
                carried = (self.carried_fluoro_time_s, self.carried_alarms)
                self.alarm_count -= self.carried_alarms
                self.carried_fluoro_time_s, self.carried_alarms = 0.0, 0
                self._schedule_alarm()
                self._emit(out, t, "alarm_reset", timer="reset", carried_fluoro_time_s=carried[0],
                           carried_alarms=carried[1])
        elif action == "hold_breath":
            if not self.breath_hold:
                self.breath_hold, self.breath_changed_t = True, t
                self._emit(out, t, "hold_breath")
        elif action == "resume_breath":
            if self.breath_hold:
                self.breath_hold, self.breath_changed_t = False, t
                self._emit(out, t, "resume_breath")
        elif action in ("breath_faster", "breath_slower"):
            self.breath_rate_steps += 1 if action == "breath_faster" else -1
            self.breath_step_t = t
            self._emit(out, t, "breath_rate", step=1 if action == "breath_faster" else -1)
        elif action in ("breath_deeper", "breath_shallower"):
            self.breath_depth_steps += 1 if action == "breath_deeper" else -1
            self.breath_step_t = t
            self._emit(out, t, "breath_depth", step=1 if action == "breath_deeper" else -1)
        return out

    def _adjust_window(self, action: str) -> None:
        """Window and level keys: steps of the profile's image.window_step (a ratio) and
        image.level_step (a fraction of the width), within a few steps of the automatic window."""
        chain = self.fl.image
        if action == "window_reset":
            self.window_scale, self.level_shift = 1.0, 0.0
        elif action.startswith("window_"):
            factor = chain.window_step if action == "window_wider" else 1.0 / chain.window_step
            self.window_scale = min(max(self.window_scale * factor, 0.25), 4.0)
        else:
            step = chain.level_step if action == "level_up" else -chain.level_step
            self.level_shift = min(max(self.level_shift + step, -0.5), 0.5)

    def _set_zoom(self, target: int) -> None:
        old_fov = self.fl.zoom_levels[self.zoom - 1].fov_mm
        new_fov = self.fl.zoom_levels[target - 1].fov_mm
        # Blades fully open stay fully open at the new field; narrower ones are clipped to it.
        h, v = (new_fov if c >= old_fov else min(c, new_fov) for c in self.collimation)
        self.collimation = (h, v)
        self.zoom = target

    def tick(self, now: float) -> list[ConsoleEvent]:
        """Advance timers, pulses and the alarm to `now`; call once per displayed frame."""
        out: list[ConsoleEvent] = []
        self._advance(now, out)
        return out

    def set_exposure_factor(self, factor: float, now: float, kvp: float | None = None,
                            ma: float | None = None) -> list[ConsoleEvent]:
        """The automatic brightness control changed the tube output to `factor` x the reference
        technique's air-kerma rate at `now`, at `kvp` and `ma` (None: tube.kvp, and tube.ma x
        `factor`, the output of a control without a kV-mA curve being the tube current's): dose
        up to `now` accrues at the old rate, after it at the new; runs record the technique."""
        out: list[ConsoleEvent] = []
        self._advance(now, out)
        self.exposure_factor = float(factor)
        tube = self.fl.tube
        self.kvp = tube.kvp if kvp is None else float(kvp)
        self.ma = tube.ma * self.exposure_factor if ma is None else float(ma)
        return out

    def note(self, t: float, kind: str, **detail) -> list[ConsoleEvent]:
        """Record something that is not a console action (an image's geometry, the trainee's
        name, an exercise step) at `t`, with the running totals, so the ledger keeps it in order."""
        out: list[ConsoleEvent] = []
        t = max(t, self._t)
        self._advance(t, out)
        self._emit(out, t, kind, **detail)
        return out

    def end(self, now: float) -> list[ConsoleEvent]:
        """Stop at `now` (session over, shutting down): an exposure in progress ends here, so its
        time and dose are recorded before the ledger closes the session."""
        out: list[ConsoleEvent] = []
        self._advance(now, out)
        self._fluoro_holders.clear()
        if self.fluoro_on:
            self._end_run(out, max(now, self._t), "session ended")
        return out

    def set_fluoroscope(self, fluoroscope: FluoroscopeProfile) -> list[ConsoleEvent]:
        """Switch to a reloaded profile at the current time, keeping what still applies."""
        out: list[ConsoleEvent] = []
        t = self._t
        exposing = self.fluoro_on
        if exposing:
            self._end_run(out, t, "profile reloaded")
        old_mode, zoom_fov = self.mode.name, self.fl.zoom_levels[self.zoom - 1].fov_mm
        self.fl = fluoroscope
        names = [m.name for m in fluoroscope.tube.modes]
        self.mode_index = names.index(old_mode) if old_mode in names else 0
        fov = fluoroscope.zoom_levels[self.zoom - 1].fov_mm
        lo = fluoroscope.collimator.min_opening_mm
        h, v = (fov if c >= zoom_fov else min(max(c, lo), fov) for c in self.collimation)
        self.collimation = (h, v)
        self._schedule_alarm()
        self._emit(out, t, "profile", fluoroscope=fluoroscope.name, mode=self.mode.name)
        if exposing:
            self._start_run(out, t, "profile reloaded")
        return out

    def _schedule_alarm(self) -> None:
        """The next alarm at the next multiple of the period of the cumulative timer (carried
        plus this session's), kept in this session's own fluoroscopy time."""
        period = self.fl.dose.alarm_period_s
        timer = self.carried_fluoro_time_s + self.fluoro_time_s
        self._next_alarm_s = period * (math.floor(timer / period + 1e-12) + 1) - self.carried_fluoro_time_s

    def carry_over(self, fluoro_time_s: float, alarms: int) -> None:
        """Continue the cumulative fluoroscopy timer and alarm count of a session a crash ended:
        21 CFR 1020.32 lets only a person reset them (alarm reset with no alarm sounding).
        The session's own totals, and so its dose record, stay its own."""
        self.carried_fluoro_time_s = max(0.0, float(fluoro_time_s))
        self.carried_alarms = max(0, int(alarms))
        self.alarm_count += self.carried_alarms
        self._schedule_alarm()

    def snapshot(self) -> ConsoleState:
        fl, mode = self.fl, self.mode
        timer = self.carried_fluoro_time_s + self.fluoro_time_s
        return ConsoleState(
            t=self._t, fluoro_on=self.fluoro_on,
            image="live" if self.fluoro_on else ("held" if self.has_image else "none"),
            mode=mode.name, pulse_rate_per_s=mode.pulse_rate_per_s, zoom=self.zoom,
            fov_mm=fl.zoom_levels[self.zoom - 1].fov_mm, collimation_mm=self.collimation,
            invert=self.invert, breath_hold=self.breath_hold, fluoro_time_s=timer,
            fluoro_time_display=minutes_and_tenths(timer), air_kerma_mgy=self.air_kerma_mgy,
            dap_gy_cm2=self.dap_gy_cm2, air_kerma_rate_mgy_per_min=self._rate() if self.fluoro_on else 0.0,
            alarm_sounding=self.alarm_sounding, alarm_count=self.alarm_count, save_count=self.save_count,
            runs=self.runs, kvp=self.kvp, ma=self.ma, pulses=self._pulse_count,
            window_scale=self.window_scale, level_shift=self.level_shift,
            breath_rate_steps=self.breath_rate_steps, breath_depth_steps=self.breath_depth_steps,
            breath_changed_t=self.breath_changed_t, breath_step_t=self.breath_step_t)
