"""Replace a file so that a crash or kill at any moment leaves the old or the new one whole.

Write to a temporary file in the same directory, fsync it, rename it over the target
(atomic on POSIX within one file system), then fsync the directory so the rename itself
survives power loss. The previous version is kept as `PATH.bak` when asked.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from .errors import FluorosimError


def _fsync_dir(directory: Path) -> None:
    fd = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def write_atomic(path: str | os.PathLike, data: bytes, *, backup: bool = False,
                 overwrite: bool = True, mode: int = 0o644) -> Path:
    """Write `data` to `path` atomically; keep the old file as `path.bak` if `backup`."""
    target = Path(path)
    directory = target.parent if str(target.parent) else Path(".")
    if not overwrite and target.exists():
        raise FluorosimError(f"{target}: already exists; refusing to overwrite it (choose another name or move it away)")
    tmp_name = None
    try:
        fd, tmp_name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=directory)
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp_name, mode)
        if backup and target.exists():
            # A hard link keeps the old inode whole as .bak while the rename below swaps in the new one.
            bak = target.with_name(target.name + ".bak")
            bak_tmp = target.with_name(f".{target.name}.bak.tmp")
            if bak_tmp.exists():
                bak_tmp.unlink()
            os.link(target, bak_tmp)
            os.replace(bak_tmp, bak)
        if not overwrite:
            # link() fails if the name appeared meanwhile: never clobber a file someone else wrote.
            os.link(tmp_name, target)
            os.unlink(tmp_name)
        else:
            os.replace(tmp_name, target)
        tmp_name = None
        _fsync_dir(directory)
    except FileExistsError:
        raise FluorosimError(f"{target}: already exists; refusing to overwrite it (choose another name or move it away)") from None
    except OSError as e:
        raise FluorosimError(f"{target}: cannot write ({e.strerror or e}); check that the folder exists, is writable "
                             "and has free space") from None
    finally:
        if tmp_name is not None and os.path.exists(tmp_name):
            os.unlink(tmp_name)
    return target
