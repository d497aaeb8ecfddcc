"""The input worker: keypad and pedal -> the console -> its state for the screen, its events for the ledger."""

from __future__ import annotations

import queue
from collections.abc import Callable, Sequence

from drivers.input_event import InputDevice

from ..config.fluoroscope import FluoroscopeProfile
from ..console.alarm_sound import AlarmSound
from ..console.state import Console, ConsoleEvent, ConsoleState
from .handoff import LatestValue, Recorded
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
                 exposure_factor: LatestValue[float]):
        super().__init__("input", idle_s=0.0)
        self.console, self.devices, self.alarm, self.console_clock = console, devices, alarm, clock
        self.console_state, self.events = console_state, events
        self.fluoroscope, self.exposure_factor = fluoroscope, exposure_factor
        self._fluoroscope_seq = 0
        self._exposure_seq = 0

    def step(self) -> bool:
        now = self.console_clock()
        console = self.console
        out: list[Recorded] = []
        switched = self.fluoroscope.newer(self._fluoroscope_seq)
        if switched is not None:
            fluoroscope, self._fluoroscope_seq = switched
            if fluoroscope is not None:
                out += _plain(console.set_fluoroscope(fluoroscope))
        events = [e for device in self.devices for e in device.poll(now)]
        for e in events:
            for ce in console.handle(e):
                # A save is written with the console's state at that press (its count names the file).
                out.append(Recorded(ce, console.snapshot() if ce.kind == "save" else None))
        # After the presses: the new tube output applies from `now`, and a press stamped before
        # `now` must not be moved to `now` by it (that would add or drop fluoroscopy time).
        exposure = self.exposure_factor.newer(self._exposure_seq)
        if exposure is not None:
            factor, self._exposure_seq = exposure
            if factor is not None:
                out += _plain(console.set_exposure_factor(factor, now))
        out += _plain(console.tick(now))
        for item in out:
            self.events.put(item)  # blocks only if the ledger is stuck (see pipeline.EVENT_QUEUE)
        snapshot = console.snapshot()
        self.alarm.update(snapshot.alarm_sounding)
        self.console_state.put(snapshot)
        self.sleep(INPUT_PERIOD_S)
        return bool(events or out)

    def teardown(self) -> None:
        if not self.stopping:
            return  # crashed: the supervisor restarts this worker with the same console
        # An exposure in progress ends now, so its time and dose reach the ledger.
        for item in _plain(self.console.end(self.console_clock())):
            self.events.put(item)
        self.console_state.put(self.console.snapshot())


def _plain(events: list[ConsoleEvent]) -> list[Recorded]:
    return [Recorded(ce) for ce in events]
