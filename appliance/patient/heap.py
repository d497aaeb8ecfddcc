"""Give the system back the heap a phase's preparation freed.

Preparing a phase (reading it, deforming a breathing state, cropping and padding it) makes and
frees arrays of tens of megabytes on the loader's thread. glibc keeps the freed pages of its
heap arenas resident for later allocations, which the appliance then never makes: after the
adult chest's six breathing states about 0.2-0.4 GB stayed resident that nothing held.
malloc_trim(0) returns them. Elsewhere than glibc it does nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools


@functools.cache
def _trim():
    name = ctypes.util.find_library("c")
    try:
        return ctypes.CDLL(name).malloc_trim if name else None
    except (OSError, AttributeError):
        return None


def release_freed() -> bool:
    """Return the heap's free pages to the system; True where the C library could."""
    trim = _trim()
    if trim is None:
        return False
    trim.argtypes = [ctypes.c_size_t]
    trim(0)
    return True
