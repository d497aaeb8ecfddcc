"""The free space kept for the dose ledger: side files (saved images, the demo's snapshots) are
not written below it.

On a nearly full disk the few MiB an admin frees would otherwise go to the next picture (a
saved image is a PNG and a DICOM of several MiB, a snapshot about one), and the dose events
held in memory would find no room again; a session's events take well under one MiB.
"""

from __future__ import annotations

import shutil
from pathlib import Path

from ..errors import FluorosimError


def check_reserve(folder: Path, reserve_mb: float, what: str) -> None:
    """Refuse, in one line, to write `what` into `folder` while its disk has less than
    `reserve_mb` MiB free (daemon.records_reserve_mb)."""
    if reserve_mb <= 0:
        return
    probe = Path(folder)
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent     # a folder not made yet lies on its nearest existing parent's disk
    try:
        free_mb = shutil.disk_usage(probe).free / 2**20
    except OSError:
        return                   # the write itself then says what is wrong with the folder
    if free_mb < reserve_mb:
        raise FluorosimError(f"{folder}: {free_mb:.1f} MiB free, under the {reserve_mb:g} MiB kept for the dose "
                             f"ledger (daemon.records_reserve_mb); {what} not written; free disk space")
