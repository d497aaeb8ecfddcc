"""LatestValue, the slot workers hand the newest value through: newest wins, skips are counted."""

from __future__ import annotations

import threading
import time

from appliance.daemon.handoff import LatestValue


def test_latest_value_gives_the_newest_and_counts_what_was_skipped():
    slot: LatestValue[int] = LatestValue()
    assert slot.get() == (None, 0)
    assert slot.newer(0) is None
    for i in range(1, 6):
        slot.put(i * 10)
    assert slot.get() == (50, 5)
    assert slot.dropped == 4  # 10..40 were overwritten unread
    assert slot.newer(5) is None
    slot.put(60)
    assert slot.newer(5) == (60, 6)
    assert slot.dropped == 4

def test_a_slow_reader_skips_stale_values_instead_of_falling_behind():
    slot: LatestValue[tuple[int, float]] = LatestValue()
    n, period = 200, 0.002
    done = threading.Event()

    def produce():
        for i in range(1, n + 1):
            slot.put((i, time.monotonic()))
            time.sleep(period)
        done.set()

    seen, ages = [], []
    t = threading.Thread(target=produce)
    t.start()
    seq = 0
    while not (done.is_set() and slot.seq == seq):
        got = slot.wait_newer(seq, 0.5)
        if got is None:
            continue
        (i, stamped), seq = got
        seen.append(i)
        ages.append(time.monotonic() - stamped)
        time.sleep(0.02)  # ten times slower than the producer
    t.join()
    assert seen == sorted(set(seen))  # always forward, never an old value twice
    assert seen[-1] == n
    assert len(seen) < n / 3
    assert slot.dropped == n - len(seen)
    # Each value read was the newest at the time: never more than a couple of producer periods old.
    assert sorted(ages)[len(ages) // 2] < 0.01

def test_wait_newer_times_out():
    slot: LatestValue[int] = LatestValue()
    t0 = time.monotonic()
    assert slot.wait_newer(0, 0.1) is None
    assert 0.09 <= time.monotonic() - t0 < 0.5
