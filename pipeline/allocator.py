"""glibc's allocator told to keep freed memory for the next array, on the detection path.

By default glibc gives a block over 128 KiB (a threshold that rises as such
blocks are freed, to at most 32 MB) its own ``mmap`` and gives it back when
it is freed; Dask's workers are told to give back everything over 64 KiB.
Detection allocates and frees the same large temporaries thousands of times:
descriptor products of 2,048 x 6,000, ICP distances, k-d tree answers.  On
a virtual machine that returns freed guest memory to its host (free page
reporting, as on this project's 2-core machines), touching such memory again
costs about 10 ms per MB, 50 to 100 times a page fault elsewhere.  Six unrelated suspects took 1,052 worker s
with Dask's setting and 785 s with this one, with the same scores
(``bench/RESULTS.md``, "Freed memory kept where detection runs").

:func:`keep_freed_memory` makes every block come from the heap and keeps up
to :data:`TRIM_THRESHOLD` of free memory at its top.  A process that has
run a detection then stays at about its peak resident memory.  Issuing keeps
glibc's way: a tile's worker gives its blocks back (``orchestrate.run``).
Elsewhere than glibc it does nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import platform

__all__ = ["keep_freed_memory", "keeps_freed_memory", "TRIM_THRESHOLD"]

TRIM_THRESHOLD = 256 * 2**20   # bytes of free memory kept at the heap's top
_M_TRIM_THRESHOLD = -1         # mallopt parameters (malloc.h)
_M_MMAP_MAX = -4

_kept = False


def keep_freed_memory():
    """Keep this process's freed memory for reuse (idempotent).

    Returns
    -------
    bool
        Whether the allocator keeps it now (False: not glibc).
    """
    global _kept
    if _kept or platform.libc_ver()[0] != "glibc":
        return _kept
    libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
    # no block of its own mapping (each freed one went back at once), and the heap's top trimmed
    # only past the threshold; mallopt returns 1 on success
    _kept = bool(libc.mallopt(_M_MMAP_MAX, 0)) and bool(libc.mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD))
    return _kept


def keeps_freed_memory():
    """Whether :func:`keep_freed_memory` took effect in this process."""
    return _kept
