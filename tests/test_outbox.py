"""The persistent outbox in the ledger's file: idempotent queueing, backoff, leases, never
twice after a success, and survival of kill -9."""

import hashlib
import os
import signal
import subprocess
import sys
import textwrap
import time

import pytest

from appliance.records.ledger import Ledger
from appliance.records.outbox import Outbox, backoff_s

T = 1_700_000_000.0


@pytest.fixture
def ledger_path(tmp_path):
    path = tmp_path / "ledger.sqlite"
    with Ledger(path):
        pass
    return path


def test_put_is_idempotent_and_adds_new_destinations(ledger_path):
    with Outbox(ledger_path, "dicom") as box:
        assert box.put("1.2.3", "image 1", b"abc", ["pacs"], session_id=4, now=T)
        assert not box.put("1.2.3", "image 1", b"other bytes", ["pacs"], now=T)
        assert box.put("1.2.3", "image 1", b"abc", ["pacs", "registry"], now=T)
        pending = box.pending(now=T)
        assert [(p.key, p.destination, p.session_id) for p in pending] == [("1.2.3", "pacs", 4), ("1.2.3", "registry", 4)]
        assert box.claim("pacs", now=T, lease_s=5)[0].payload == b"abc"     # the first bytes queued are kept
    with Outbox(ledger_path, "xapi") as other_kind:
        assert other_kind.pending(now=T) == [] and other_kind.claim("pacs", now=T, lease_s=5) == []


def test_a_delivered_object_is_never_handed_out_again(ledger_path):
    with Outbox(ledger_path, "dicom") as box:
        box.put("a", "a", b"1", ["pacs"], now=T)
        box.put("b", "b", b"2", ["pacs"], now=T)
        first, second = box.claim("pacs", now=T, lease_s=5)
        box.delivered(first, now=T + 1)
        box.failed(second, "timed out", first_delay_s=10, max_delay_s=60, now=T + 1)
        box.delivered(first, now=T + 2)          # a second confirmation changes nothing
        box.put("a", "a", b"1", ["pacs"], now=T + 3)
        later = box.claim("pacs", now=T + 1000, lease_s=5, ignore_backoff=True)
        assert [i.key for i in later] == ["b"]
        assert box.sent_keys("pacs") == ["a"]


def test_backoff_doubles_to_the_ceiling(ledger_path):
    # Hand-worked: 10 s, then 20, 40, then the 60 s ceiling.
    assert [backoff_s(n, 10.0, 60.0) for n in range(1, 7)] == [10, 20, 40, 60, 60, 60]
    with Outbox(ledger_path, "dicom") as box:
        box.put("x", "x", b"x", ["pacs"], now=T)
        now = T
        for wait in (10, 20, 40, 60, 60):
            (item,) = box.claim("pacs", now=now, lease_s=5)
            due = box.failed(item, "connection refused", first_delay_s=10, max_delay_s=60, now=now)
            assert due == now + wait
            assert box.claim("pacs", now=due - 0.001, lease_s=5) == []
            now = due
        (p,) = box.pending(now=now)
        assert p.attempts == 5 and p.last_error == "connection refused"


def test_a_lease_keeps_a_second_sender_off_until_it_expires(ledger_path):
    with Outbox(ledger_path, "dicom") as one, Outbox(ledger_path, "dicom") as two:
        one.put("k", "k", b"k", ["pacs"], now=T)
        assert len(one.claim("pacs", now=T, lease_s=30)) == 1
        assert two.claim("pacs", now=T + 29, lease_s=30) == []
        assert [i.key for i in two.claim("pacs", now=T + 31, lease_s=30)] == ["k"]   # the first sender died


CLAIMER = textwrap.dedent("""
    import os, signal, sys
    from appliance.records.outbox import Outbox
    box = Outbox(sys.argv[1], "dicom")
    assert len(box.claim("pacs", lease_s=3600)) == 1
    os.kill(os.getpid(), signal.SIGKILL)
""")


def test_the_lease_of_a_killed_sender_is_taken_over_at_once(ledger_path):
    with Outbox(ledger_path, "dicom") as box:
        box.put("k", "k", b"k", ["pacs"])
        child = subprocess.run([sys.executable, "-c", CLAIMER, str(ledger_path)], env={**os.environ, "PYTHONPATH": os.getcwd()})
        assert child.returncode == -signal.SIGKILL
        # Leased for an hour by a process that no longer exists: handed out again now.
        assert [i.key for i in box.claim("pacs", lease_s=30)] == ["k"]


WRITER = textwrap.dedent("""
    import hashlib, sys
    from appliance.records.outbox import Outbox
    box = Outbox(sys.argv[1], "dicom")
    n = 0
    while True:
        key = f"obj-{n}"
        box.put(key, key, hashlib.sha256(key.encode()).digest() * 2048, ["pacs", "registry"])
        print(n, flush=True)
        n += 1
""")


def test_kill_9_while_queueing_leaves_whole_objects_only(ledger_path):
    child = subprocess.Popen([sys.executable, "-c", WRITER, str(ledger_path)], stdout=subprocess.PIPE, text=True,
                             cwd=os.getcwd(), env={**os.environ, "PYTHONPATH": os.getcwd()})
    confirmed = -1
    deadline = time.monotonic() + 20
    while confirmed < 30 and time.monotonic() < deadline:
        confirmed = int(child.stdout.readline())
    os.kill(child.pid, signal.SIGKILL)
    child.wait()
    # Lines the writer printed before the kill but not yet read: it had confirmed those too.
    rest = child.stdout.read().split()
    confirmed = int(rest[-1]) if rest else confirmed
    child.stdout.close()
    assert confirmed >= 30
    with Outbox(ledger_path, "dicom") as box:
        pending = box.pending()
        keys = sorted({p.key for p in pending}, key=lambda k: int(k.split("-")[1]))
        # Everything put() confirmed is there; at most the one in progress beyond it.
        assert keys[: confirmed + 1] == [f"obj-{n}" for n in range(confirmed + 1)] and len(keys) <= confirmed + 2
        for name in ("pacs", "registry"):
            items = box.claim(name, lease_s=5, limit=1000)
            assert [i.key for i in items] == keys          # each object with both its deliveries, or not at all
            assert all(i.payload == hashlib.sha256(i.key.encode()).digest() * 2048 for i in items)
