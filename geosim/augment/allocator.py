"""Keep freed memory in the process for the next augmented output (glibc only).

An augmented 5000² RGB pair allocates ≈ 0.8 GB of fresh large arrays (warped image
and mask, warp fields, photometric output, for each image). glibc serves every
allocation above 32 MB with its own ``mmap`` and unmaps it when freed, so each of them
costs the kernel a page fault and a page zeroing per page on first touch: ≈ 0.2–0.3 s of
system time per pair, 11–15 % of the pipeline's CPU (measured: ``sys`` 0.26–0.28 s per
pair, 8000 minor faults; docs/augmentation.md). With mmap disabled and trimming off, large
arrays come from the heap and a freed one is reused, already mapped, by the next output
(``sys`` 0.06–0.07 s, 1000 faults per pair) at the same peak resident memory (841 vs
845 MB over 10 pairs): the heap keeps its peak, which the next output needs anyway.

:func:`geosim.heap.keep_freed_heap` (which every engine applies before its tasks) raises
glibc's mmap and trim thresholds for GDAL's small blocks but cannot help arrays above
glibc's 32 MB mmap cap; this goes further for the augmentation's tasks, and applies that
function first so that its later first call cannot lower the trim threshold again.

Only the main arena obeys this: tasks run by a thread other than the process's first
(a Dask worker's executor thread) get their large arrays from ``mmap`` whatever is set
here, unless the process was started with ``MALLOC_ARENA_MAX=1`` in its environment.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import sys

from geosim.heap import keep_freed_heap

__all__ = ["keep_freed_memory"]

#: mallopt parameters (glibc's malloc.h).
_M_TRIM_THRESHOLD = -1
_M_MMAP_MAX = -4

#: Heap top kept when memory is freed, bytes (never trimmed in practice).
_TRIM_THRESHOLD_BYTES = 2**31 - 1

_done = False


def keep_freed_memory() -> bool:
    """Serve large allocations from the heap and never trim it (once per process).

    Returns
    -------
    bool
        Whether glibc accepted the settings (False on other C libraries and platforms,
        where nothing is changed).
    """
    global _done
    if _done:
        return True
    if not sys.platform.startswith("linux"):
        return False
    keep_freed_heap()  # its one-time settings first: it must not undo these later
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    _done = bool(mallopt(_M_MMAP_MAX, 0)) and bool(mallopt(_M_TRIM_THRESHOLD,
                                                            _TRIM_THRESHOLD_BYTES))
    return _done
