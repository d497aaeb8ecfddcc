"""The log queue: a version header first, every thread's lines, nothing dropped."""

from __future__ import annotations

import logging
import os
import threading

from appliance import __version__
from appliance.daemon.logqueue import start_logging


def test_log_file_starts_with_the_version_header_and_gets_every_thread(tmp_path):
    root = logging.getLogger()
    before = list(root.handlers), root.level
    logs = start_logging(tmp_path / "logs", stream=open(os.devnull, "w"))
    try:
        def talk(k):
            for i in range(50):
                logging.getLogger("test.worker").info("worker %d line %d", k, i)

        threads = [threading.Thread(target=talk, args=(k,)) for k in range(4)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    finally:
        logs.stop()
        root.handlers[:] = before[0]
        root.setLevel(before[1])
    text = (tmp_path / "logs" / "fluorosim.log").read_text()
    first = text.splitlines()[0]
    assert first.startswith(f"# fluorosim {__version__} | Python ")
    assert f"pid {os.getpid()}" in first
    for k in range(4):
        for i in (0, 49):
            assert f"worker {k} line {i}" in text
    assert logs.dropped == 0
