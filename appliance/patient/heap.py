"""Give the system back the heap the appliance frees.

Preparing a phase (reading it, deforming a breathing state, cropping and padding it) makes and
frees arrays of tens of megabytes on the loader's thread. glibc keeps the freed pages of its
heap arenas resident for later allocations, which the appliance then never makes: after the
adult chest's six breathing states about 0.2-0.4 GB stayed resident that nothing held.
malloc_trim(0) returns them (`release_freed`).

The renderer's buffers come and go every frame (a cast's integrals, 1-8 MB; slab and layout
copies of a phase, 20-40 MB, with PoCL in host memory). glibc gives a block of its own pages
(mmap) only to requests above a threshold that rises to the largest such block freed, up to
32 MiB: once the first phase's copies were freed, every frame's buffers came from the arenas,
fragmented them, and the resident size of a breathing patient's session grew by a third in
five minutes. A fixed threshold (`keep_large_blocks_apart`) keeps those blocks out of the
arenas. Elsewhere than glibc both do nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools

#: Requests from this size up get pages of their own, returned to the system when freed; below
#: it (the moving frames' images and integrals at 256 and under, 1 MB or less) the arenas serve
#: them again without a page fault.
MMAP_THRESHOLD_BYTES = 4 * 2**20
#: mallopt's parameter number for the threshold (malloc.h).
_M_MMAP_THRESHOLD = -3


@functools.cache
def _libc():
    name = ctypes.util.find_library("c")
    try:
        return ctypes.CDLL(name) if name else None
    except OSError:
        return None


def _function(name: str):
    return getattr(_libc(), name, None)


def release_freed() -> bool:
    """Return the heap's free pages to the system; True where the C library could."""
    trim = _function("malloc_trim")
    if trim is None:
        return False
    trim.argtypes = [ctypes.c_size_t]
    trim(0)
    return True


def keep_large_blocks_apart(threshold_bytes: int = MMAP_THRESHOLD_BYTES) -> bool:
    """Fix the size from which glibc's malloc maps a block of its own (see the module's
    docstring); True where the C library took it. For the whole process, from now on."""
    mallopt = _function("mallopt")
    if mallopt is None:
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    return bool(mallopt(_M_MMAP_THRESHOLD, int(threshold_bytes)))
