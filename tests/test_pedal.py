"""The serial foot pedal over a real pty pair with real pyserial."""

import os

import pytest

from drivers.input_event import REOPEN_INTERVAL_S
from drivers.pedal import SerialPedal


@pytest.fixture
def pty_link(tmp_path):
    """A pty pair, with the pedal side reached through a symlink (as udev's /dev/fluorosim/pedal)."""
    master, slave = os.openpty()
    link = tmp_path / "pedal"
    link.symlink_to(os.ttyname(slave))
    yield master, link
    os.close(master)
    os.close(slave)


def settle():
    # A pty hands bytes over at once, but give the kernel a moment on a loaded machine.
    import time
    time.sleep(0.02)


def test_press_heartbeat_release(pty_link):
    master, link = pty_link
    p = SerialPedal(str(link), silence_timeout_s=0.5, now=0.0)
    assert p.state == "ok" and p.fileno() >= 0
    os.write(master, b"HB\r\nDOWN\r\n")
    settle()
    evs = p.poll(0.1)
    assert [(e.key, e.pressed, e.source, e.t_monotonic) for e in evs] == [("pedal", True, "pedal", 0.1)]
    # Heartbeats keep it pressed past the silence timeout.
    for t in (0.4, 0.8, 1.2):
        os.write(master, b"HB\n")
        settle()
        assert p.poll(t) == []
    assert p.pressed
    # A line split across reads is joined.
    os.write(master, b"U")
    settle()
    assert p.poll(1.3) == []
    os.write(master, b"P\n")
    settle()
    assert [(e.key, e.pressed) for e in p.poll(1.4)] == [("pedal", False)]
    p.close()


def test_silent_pedal_counts_as_released(pty_link):
    master, link = pty_link
    p = SerialPedal(str(link), silence_timeout_s=0.5, now=0.0)
    os.write(master, b"DOWN\n")
    settle()
    assert p.poll(1.0)[0].pressed
    assert p.poll(1.4) == []
    evs = p.poll(1.6)                                # 0.6 s without a line
    assert [(e.pressed, e.t_monotonic) for e in evs] == [(False, 1.6)]
    assert p.state == "unplugged" and "silent" in p.problem
    # It answers again: ok, but still released until it says DOWN.
    os.write(master, b"HB\n")
    settle()
    assert p.poll(1.7) == [] and p.state == "ok" and not p.pressed


def test_custom_protocol_lines(pty_link):
    master, link = pty_link
    p = SerialPedal(str(link), press_line="P1", release_line="P0", heartbeat_line="ALIVE", silence_timeout_s=2.0)
    os.write(master, b"DOWN\nP1\n")
    settle()
    assert [e.pressed for e in p.poll(0.1)] == [True]
    os.write(master, b"P0\n")
    settle()
    assert [e.pressed for e in p.poll(0.2)] == [False]


def test_unplug_releases_and_replug_reattaches(pty_link, monkeypatch):
    master, link = pty_link
    p = SerialPedal(str(link), silence_timeout_s=5.0, now=0.0)
    os.write(master, b"DOWN\n")
    settle()
    assert p.poll(0.1)[0].pressed
    target = os.readlink(link)
    link.unlink()                                     # udev removes the symlink on unplug
    evs = p.poll(0.2)
    assert [(e.pressed) for e in evs] == [False] and p.state == "unplugged" and "unplugged" in p.problem
    assert p.poll(0.5) == [] and p.state == "unplugged"
    link.symlink_to(target)                           # plugged back in
    assert p.poll(0.2 + REOPEN_INTERVAL_S + 0.01) == []
    assert p.state == "ok"
    os.write(master, b"DOWN\n")
    settle()
    assert [e.pressed for e in p.poll(1.5)] == [True]


def test_missing_port_says_so():
    from appliance.console.inputs import problems
    from drivers.input_event import NoInput
    p = SerialPedal("/dev/fluorosim-no-such-pedal")
    assert p.state == "unplugged" and "cannot open the pedal" in p.problem and p.poll(0.0) == []
    assert problems([NoInput(), p]) == [p.problem] and "/dev/fluorosim-no-such-pedal" in p.problem
