"""The ledger's reserve of free space (records/disk_reserve.check_reserve, daemon.records_reserve_mb)
on a file system of known size: its unit, its edge and its off switch.

Ground truth: a tmpfs mounted with size=4m holds 4 MiB (4,194,304 bytes, 1,024 pages of
4 KiB); a file of 1 MiB written into it leaves 3 MiB. The reserve is in MiB (2^20 bytes), so
4 MiB free is under a reserve of 4.1 though it is 4.19 MB (10^6 bytes).
"""

from __future__ import annotations

import os
import subprocess

import pytest

from appliance.errors import FluorosimError
from appliance.records.disk_reserve import check_reserve


@pytest.fixture
def small_disk(tmp_path):
    mnt = tmp_path / "mnt"
    mnt.mkdir()
    result = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=4m", "tmpfs", str(mnt)], capture_output=True)
    if result.returncode != 0:
        pytest.skip("cannot mount a small tmpfs here (needs root); the reserve's edges use a file system of known size")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", "-l", str(mnt)], check=False)


def test_the_reserve_is_in_mib_and_refused_just_under_it(small_disk):
    check_reserve(small_disk, 4.0, "a test image")                 # 4 MiB free: not under 4 MiB
    with pytest.raises(FluorosimError) as refused:
        check_reserve(small_disk, 4.1, "a test image")             # 4 MiB is under 4.1 MiB (not 4.19 MB)
    msg = str(refused.value)
    assert msg.startswith(f"{small_disk}: 4.0 MiB free, under the 4.1 MiB") and "records_reserve_mb" in msg
    assert "a test image not written" in msg and "\n" not in msg
    with open(small_disk / "filler", "wb") as f:
        f.write(b"\0" * 2**20)
        f.flush()
        os.fsync(f.fileno())
    check_reserve(small_disk, 3.0, "a test image")
    with pytest.raises(FluorosimError, match="3.0 MiB free, under the 3.05 MiB"):
        check_reserve(small_disk, 3.05, "a test image")


def test_a_folder_not_made_yet_is_measured_on_its_nearest_existing_parent(small_disk):
    with pytest.raises(FluorosimError, match="4.0 MiB free"):
        check_reserve(small_disk / "snapshots" / "today", 8.0, "snapshot 01-first.png")


def test_a_reserve_of_zero_or_less_is_off_even_on_a_full_disk(small_disk):
    with open(small_disk / "filler", "wb") as f:
        try:
            while True:
                f.write(b"\0" * 65536)
                f.flush()
        except OSError:
            pass
    with pytest.raises(FluorosimError, match="0.0 MiB free"):
        check_reserve(small_disk, 0.001, "a test image")
    check_reserve(small_disk, 0.0, "a test image")
    check_reserve(small_disk, -1.0, "a test image")
