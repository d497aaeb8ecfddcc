"""A saved image re-rendered at the detector's native matrix beside the live view.

On a CPU device the native frame (1024 x 1024 on the shipped profiles) costs a second or
more, on the same cores as the live frames. It is cast in bands of rows (Caster.cast), and
between bands it waits, while live frames are coming, for as long as its share of the device
allows: the live view keeps most of its frame rate, and the save takes longer. With no live
frame coming (fluoroscopy off, the last image held) the bands run back to back.

The waiting happens in the callback the cast asks between bands, in slices, so whoever
passed `cancelled` (the records worker, which records the dose events that came in
meanwhile) is asked again every slice, never only once per band.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable

import numpy as np

from ..config.appliance import Daemon
from ..config.fluoroscope import FluoroscopeProfile
from ..xray.renderer import View

#: The longest the pacing sleeps before asking the caller's callback again (s).
PACE_SLICE_S = 0.02
#: Live frames count as coming while the last one went on screen within this long (s): a few
#: live frame periods on a CPU device, well under the held image's refresh period.
LIVE_GAP_S = 0.25


class SavePacer:
    """The callback a banded cast asks between bands: holds the save back to `share` of the
    time while `live()` says live frames are coming, asking `cancelled` every slice."""

    def __init__(self, share: float, cancelled: Callable[[], bool] | None = None,
                 live: Callable[[], bool] | None = None, clock: Callable[[], float] = time.monotonic,
                 sleep: Callable[[float], None] = time.sleep):
        self.share, self.cancelled, self.live, self.clock, self.sleep = share, cancelled, live, clock, sleep
        self._resumed = clock()
        #: Longest time (s) between two calls of `cancelled`: how late an event waiting for it can be.
        self.longest_gap_s = 0.0
        self._asked = self._resumed

    def _ask(self) -> bool:
        now = self.clock()
        self.longest_gap_s = max(self.longest_gap_s, now - self._asked)
        self._asked = now
        return bool(self.cancelled()) if self.cancelled is not None else False

    def __call__(self) -> bool:
        if self._ask():
            return True
        now = self.clock()
        # The band just cast (with any wait for the lock a live frame held) took this long; the
        # live view gets (1 - share) / share of it before the next band.
        until = now + (now - self._resumed) * (1.0 - self.share) / self.share
        while self.live is not None and self.live() and until - now > 1e-6:    # (not a rounding's remainder)
            self.sleep(min(PACE_SLICE_S, until - now))
            if self._ask():
                return True
            now = self.clock()
        self._resumed = self.clock()
        return False


Native = tuple[np.ndarray, FluoroscopeProfile]


def native_frame(renderer, request: tuple, native_fl: FluoroscopeProfile, daemon: Daemon, cpu: bool,
                 cancelled: Callable[[], bool] | None = None,
                 live: Callable[[], bool] | None = None) -> tuple[Native, SavePacer | None]:
    """The live view `request` = (volume, T_xray_from_ct, view, blend) again at the detector's
    native matrix (`native_fl`'s detector) with the recursive filter settled, 16-bit, and the profile read out at that
    matrix; on a CPU device (`cpu`) cast in daemon.save_bands bands paced to
    daemon.save_device_share of the time while `live()`. Returns it with the pacer (None off
    a CPU device)."""
    volume, T, view, blend = request
    native = renderer.at_matrix(native_fl.detector.columns, native_fl.detector.rows)
    pacer = SavePacer(daemon.save_device_share, cancelled, live) if cpu else None
    settled: View = dataclasses.replace(view, temporal="settled")
    frame = native.render(volume, T, settled, blend=blend, bands=daemon.save_bands if cpu else None,
                          cancelled=pacer if pacer is not None else cancelled)
    image = np.rint(np.clip(frame.image, 0.0, 1.0) * 65535.0).astype(np.uint16)
    return (image, native.fluoroscope), pacer
