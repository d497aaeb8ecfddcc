"""The input worker: keypad and pedal -> the console -> its state for the screen, its events for the ledger."""

from __future__ import annotations

import queue
from collections.abc import Callable, Sequence

from drivers.input_event import InputDevice

from ..config.fluoroscope import FluoroscopeProfile
from ..console.alarm_sound import AlarmSound
from ..console.state import Console, ConsoleEvent, ConsoleState
from ..teaching.live import LiveTeaching, TeachingStatus
from .handoff import LatestValue, Recorded, Technique
from .worker import Worker

#: How often the worker polls the keypad and pedal and advances the console (s).
INPUT_PERIOD_S = 0.005


class InputWorker(Worker):
    """keypad.poll() + pedal.poll() -> Console.handle() / Console.tick() -> `console_state` (newest)
    and `events` (every one: each is a dose record).

    The console lives on this thread alone: a reloaded fluoroscope and the tube output the
    automatic brightness control set arrive in slots and are applied here.
    """

    def __init__(self, console: Console, devices: Sequence[InputDevice], alarm: AlarmSound,
                 clock: Callable[[], float], *, console_state: LatestValue[ConsoleState],
                 events: queue.Queue[Recorded], fluoroscope: LatestValue[FluoroscopeProfile],
                 exposure_factor: LatestValue[Technique], teaching: LiveTeaching | None = None,
                 views: LatestValue[tuple[float, dict]] | None = None,
                 teaching_status: LatestValue[TeachingStatus] | None = None, badge: InputDevice | None = None):
        super().__init__("input", idle_s=0.0)
        self.console, self.devices, self.alarm, self.console_clock = console, devices, alarm, clock
        self.console_state, self.events = console_state, events
        self.fluoroscope, self.exposure_factor = fluoroscope, exposure_factor
        self._fluoroscope_seq = 0
        self._exposure_seq = 0
        # Teaching runs on this thread beside the console: its records go through Console.note.
        self.teaching, self.views, self.teaching_status = teaching, views, teaching_status
        # A badge reader types the trainee's name: its keys never reach the console.
        self.badge = badge
        self._view_seq = 0

    def step(self) -> bool:
        now = self.console_clock()
        console = self.console
        out: list[Recorded] = []
        switched = self.fluoroscope.newer(self._fluoroscope_seq)
        if switched is not None:
            fluoroscope, self._fluoroscope_seq = switched
            if fluoroscope is not None:
                out += _plain(console.set_fluoroscope(fluoroscope))
        teaching = self.teaching
        if teaching is not None and self.views is not None:
            shown = self.views.newer(self._view_seq)
            if shown is not None:
                view, self._view_seq = shown
                if view is not None:
                    out += _plain(teaching.offer_view(console, *view))
        if teaching is not None and self.badge is not None:
            for e in self.badge.poll(now):
                out += _plain(teaching.handle(console, e))
        events = [e for device in self.devices for e in device.poll(now)]
        for e in events:
            done = console.handle(e)
            for ce in done:
                # A save is written with the console's state at that press (its count names the file).
                out.append(Recorded(ce, console.snapshot() if ce.kind == "save" else None))
            if teaching is not None:
                out += _plain(teaching.after(console, done) + teaching.handle(console, e))
        # After the presses: the new tube output applies from `now`, and a press stamped before
        # `now` must not be moved to `now` by it (that would add or drop fluoroscopy time).
        exposure = self.exposure_factor.newer(self._exposure_seq)
        if exposure is not None:
            technique, self._exposure_seq = exposure
            if technique is not None:
                out += _plain(console.set_exposure_factor(technique.factor, now, technique.kvp, technique.ma))
        out += _plain(console.tick(now))
        for item in out:
            self.events.put(item)  # blocks only if the ledger is stuck (see pipeline.EVENT_QUEUE)
        snapshot = console.snapshot()
        self.alarm.update(snapshot.alarm_sounding)
        self.console_state.put(snapshot)
        if teaching is not None and self.teaching_status is not None:
            self.teaching_status.put(teaching.status())
        self.sleep(INPUT_PERIOD_S)
        return bool(events or out)

    def teardown(self) -> None:
        if not self.stopping:
            return  # crashed: the supervisor restarts this worker with the same console
        # An exercise still running and an exposure in progress end now, so they reach the ledger.
        now = self.console_clock()
        if self.teaching is not None:
            for item in _plain(self.teaching.end(self.console, now)):
                self.events.put(item)
        for item in _plain(self.console.end(now)):
            self.events.put(item)
        self.console_state.put(self.console.snapshot())


def _plain(events: list[ConsoleEvent]) -> list[Recorded]:
    return [Recorded(ce) for ce in events]
