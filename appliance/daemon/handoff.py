"""`LatestValue`: how workers hand each other data without ever falling behind.

A one-element slot that every `put` overwrites. A reader gets the newest value and its
sequence number; a value overwritten before anyone read it is counted as dropped. A slow
renderer therefore always draws the newest pose and skips stale ones, where a queue
would make it draw every old pose, later and later.
"""

from __future__ import annotations

import threading
import time
from typing import Generic, TypeVar

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
