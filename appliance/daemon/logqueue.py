"""Logging through a bounded queue to one background writer, so the frame loop never waits on disk.

Records go from any thread into a queue; a listener thread writes them to stderr (which
systemd sends to the journal) and to a rotating file in data_dir/logs. Each new log file
starts with a version header: what ran, on what, since when - the first thing support asks.
A full queue drops records and counts them rather than stalling a worker.
"""

from __future__ import annotations

import logging
import logging.handlers
import os
import platform
import queue
import sys
import time
from pathlib import Path

from .. import __version__

LOG_FORMAT = "%(asctime)s %(levelname)s %(threadName)s %(name)s: %(message)s"
#: Records waiting for the writer; beyond this they are dropped and counted.
QUEUE_RECORDS = 10_000


def version_header() -> str:
    """One line naming the software and machine, written at the top of every log file."""
    versions = []
    for module in ("numpy", "pyopencl", "cv2", "pydantic"):
        mod = sys.modules.get(module)
        if mod is not None:
            versions.append(f"{module} {getattr(mod, '__version__', '?')}")
    return (f"fluorosim {__version__} | Python {platform.python_version()} | {platform.platform()} | "
            + (" | ".join(versions) + " | " if versions else "")
            + f"pid {os.getpid()} | started {time.strftime('%Y-%m-%dT%H:%M:%S%z')}")


class _DroppingQueueHandler(logging.handlers.QueueHandler):
    def __init__(self, q: queue.Queue):
        super().__init__(q)
        self.dropped = 0

    def enqueue(self, record: logging.LogRecord) -> None:
        try:
            self.queue.put_nowait(record)
        except queue.Full:
            self.dropped += 1


class _HeaderRotatingFileHandler(logging.handlers.RotatingFileHandler):
    """A rotating file whose every new file begins with the version header.

    A record the disk refuses (full, read-only) is counted and dropped: the log is a side
    task and must never print a traceback per record or stop what is being logged.
    """

    failed = 0

    def handleError(self, record: logging.LogRecord) -> None:
        self.failed += 1

    def _open(self):
        stream = super()._open()
        if stream.tell() == 0:
            stream.write(f"# {version_header()}\n")
        else:
            stream.write(f"# --- restarted: {version_header()}\n")
        stream.flush()
        return stream


class LogQueue:
    """The running log set-up; `stop()` writes out what is queued and restores the root logger."""

    def __init__(self, handler: _DroppingQueueHandler, listener: logging.handlers.QueueListener,
                 targets: list[logging.Handler], path: Path | None, problem: str | None = None):
        self.handler, self.listener, self.targets, self.path = handler, listener, targets, path
        #: Why the log file could not be opened (the journal still gets every record), or None.
        self.problem = problem

    @property
    def failed_writes(self) -> int:
        """Records the log file's disk refused (full or read-only) since start."""
        return sum(getattr(t, "failed", 0) for t in self.targets)

    @property
    def dropped(self) -> int:
        return self.handler.dropped

    def stop(self) -> None:
        root = logging.getLogger()
        root.removeHandler(self.handler)
        self.listener.stop()
        for t in self.targets:
            try:
                t.close()
            except OSError:
                pass  # a full disk refuses the last buffered bytes; the journal has them


def start_logging(log_dir: Path | None, *, level: int = logging.INFO, stream=None, console_level: int = logging.NOTSET,
                  max_mb: float = 10.0, backups: int = 5) -> LogQueue:
    """Send the root logger through a queue to stderr and (if `log_dir`) data_dir/logs/fluorosim.log.

    `console_level` raises the threshold for stderr only (the demo prints its own progress).
    """
    targets: list[logging.Handler] = []
    formatter = logging.Formatter(LOG_FORMAT)
    console = logging.StreamHandler(stream if stream is not None else sys.stderr)
    console.setFormatter(formatter)
    console.setLevel(console_level)
    targets.append(console)
    path, problem = None, None
    if log_dir is not None:
        log_dir = Path(log_dir)
        try:
            log_dir.mkdir(parents=True, exist_ok=True)
            f = _HeaderRotatingFileHandler(log_dir / "fluorosim.log", maxBytes=int(max_mb * 2**20),
                                           backupCount=backups, encoding="utf-8")
        except OSError as e:
            # A full or read-only disk must not keep the appliance from starting: the journal
            # (stderr) still gets every record, and the disk health check says so on screen.
            problem = f"{log_dir}: cannot write the log file ({e.strerror or e}); logging to the journal only"
        else:
            path = log_dir / "fluorosim.log"
            f.setFormatter(formatter)
            targets.append(f)
    q: queue.Queue = queue.Queue(maxsize=QUEUE_RECORDS)
    handler = _DroppingQueueHandler(q)
    listener = logging.handlers.QueueListener(q, *targets, respect_handler_level=True)
    root = logging.getLogger()
    root.addHandler(handler)
    root.setLevel(level)
    listener.start()
    logging.getLogger(__name__).info("%s", version_header())
    if problem:
        logging.getLogger(__name__).warning("%s", problem)
    return LogQueue(handler, listener, targets, path, problem)
