"""`LatestValue`: how workers hand each other data without ever falling behind, and the
values they hand each other.

A one-element slot that every `put` overwrites. A reader gets the newest value and its
sequence number; a value overwritten before anyone read it is counted as dropped. A slow
renderer therefore always draws the newest pose and skips stale ones, where a queue
would make it draw every old pose, later and later.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Generic, TypeVar

import numpy as np

from ..console.state import ConsoleEvent, ConsoleState
from ..tracking.tracker import Pose
from ..xray.renderer import PreparedVolume

T = TypeVar("T")


class LatestValue(Generic[T]):
    """The newest value put, with its sequence number (0 = nothing put yet)."""

    def __init__(self, name: str = ""):
        self.name = name
        self._cond = threading.Condition()
        self._value: T | None = None
        self._seq = 0
        self._read_seq = 0
        self.dropped = 0

    def put(self, value: T) -> int:
        """Replace the value; returns its sequence number."""
        with self._cond:
            if self._seq > self._read_seq:
                self.dropped += 1
            self._seq += 1
            self._value = value
            self._cond.notify_all()
            return self._seq

    def get(self) -> tuple[T | None, int]:
        """The newest value and its sequence number; (None, 0) before the first put. Never blocks."""
        with self._cond:
            self._read_seq = self._seq
            return self._value, self._seq

    def newer(self, after_seq: int) -> tuple[T | None, int] | None:
        """The newest value if its sequence number is above `after_seq`, else None. Never blocks."""
        with self._cond:
            if self._seq <= after_seq:
                return None
            self._read_seq = self._seq
            return self._value, self._seq

    def wait_newer(self, after_seq: int, timeout_s: float) -> tuple[T | None, int] | None:
        """Like `newer`, but waits up to `timeout_s` seconds for a value to arrive."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while self._seq <= after_seq:
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                self._cond.wait(left)
            self._read_seq = self._seq
            return self._value, self._seq

    @property
    def seq(self) -> int:
        with self._cond:
            return self._seq


@dataclass(frozen=True)
class TrackedPose:
    """capture -> render: the phantom's pose in one camera frame."""

    pose: Pose
    t_frame: float            # camera frame timestamp (time.monotonic, s)
    seq: int                  # camera frame sequence number
    t_picked: float | None = None     # when the capture worker took the frame (time.monotonic, s)
    t_tracked: float | None = None    # when the pose was ready, filtered (time.monotonic, s)
    filter_s: float = 0.0             # of that, the time in the pose filter (s)


@dataclass(frozen=True)
class PhaseValue:
    """phases -> render: the patient now, as one prepared phase or a blend of two."""

    prepared_a: PreparedVolume
    prepared_b: PreparedVolume | None
    weight: float             # weight of `prepared_b` in [0, 1)
    generation: int           # which renderer prepared it: values of a replaced renderer are not drawn
    t_case_s: float | None = None  # the case time it stands for (s), for the teaching records' phase windows
    breathing: str = ""       # the breathing model's line for the monitor (rate, depth, held); "" without one
    inspired: float | None = None  # the breath: 0 end-expiration .. 1 end-inspiration (None: no breathing model)
    #: Phases the patient will need within PhaseWorker's look ahead that this value does not
    #: hold: a view held at rest casts them beside the live frames before they are drawn.
    upcoming: tuple[PreparedVolume, ...] = ()


@dataclass(frozen=True)
class Recorded:
    """input -> records: one console event, with the console's state at a save press (its count names the file)."""

    event: ConsoleEvent
    save_state: ConsoleState | None = None


@dataclass(frozen=True)
class Technique:
    """render -> input: the technique the exposure control set for the latest image."""

    factor: float               # air-kerma rate relative to the reference technique (the console doses at it)
    kvp: float | None = None    # tube voltage (kV); None: the profile's tube.kvp
    ma: float | None = None     # tube current (mA); None: the profile's tube.ma


@dataclass(frozen=True)
class ShownImage:
    """render -> records: the newest live image and the pose it was rendered at, together, so a
    save writes the angulation of the image it saves."""

    image: np.ndarray
    T_xray_from_ct: np.ndarray     # 4x4, mm


@dataclass(frozen=True)
class SavedImage:
    """records -> render: an image just written, so the screen can flash "saved"."""

    png: Path
    dicom: Path
    t_saved: float            # time.monotonic when written (s)


@dataclass
class ShownFrame:
    """What the display shows now; handed to observers (the demo's snapshots) after each write."""

    rgb_source: Callable[[], np.ndarray]   # reads the framebuffer back
    image: np.ndarray | None               # the rendered image in [0, 1] (last-image-hold keeps it)
    state: ConsoleState
    pose: TrackedPose | None
    live: bool                             # a new image was rendered for this write
    t_wall: float
    latency_s: float | None
    banners: list[str]
    saved_flash: bool
    inspired: float | None = None          # the breath of a live image (0 end-expiration, 1 end-inspiration)
    t_case_s: float | None = None          # the case time a live image's patient was drawn at (s)
