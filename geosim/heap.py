"""Keep freed heap memory in the process instead of returning it to the kernel at once.

A task that decodes a 5000 px tile allocates and frees GDAL cache blocks of ≈ 200 KB
by the thousand. With glibc's defaults those above the mmap threshold are mapped and
unmapped one by one, and a freed heap top is trimmed: every next block is a fresh
mapping whose pages fault in (≈ 10 000 page faults per tile). Dask's worker processes
make it worse: their nanny starts them with ``MALLOC_TRIM_THRESHOLD_=65536``
(``distributed.nanny.pre-spawn-environ``), which also switches off glibc's dynamic
raising of both thresholds. :func:`keep_freed_heap` raises them once per process, so
freed blocks are reused: page faults of a tile's read 10 300 → 4 800 (docs/scale.md);
its CPU effect was within the noise of the loaded machine it was measured on. The peak
memory of the degrade command did not change (329–334 MB, main's 329 MB,
benchmarks/bench_degrade_command.py); what the process gave back between tasks (at most
:data:`TRIM_THRESHOLD_BYTES` at the heap's top) stays resident. A no-op where the C
library is not glibc.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import threading

#: Allocations below this come from the heap, above it from their own mapping (glibc
#: caps it at 32 MiB on 64-bit systems).
MMAP_THRESHOLD_BYTES = 32 << 20
#: Free memory at the heap's top kept before it is returned to the kernel. With these two
#: values a worker behaves as glibc's own dynamic thresholds settle in a plain process
#: (the mmap threshold rises to the largest freed mapping, up to 32 MiB, and the trim
#: threshold to twice that), which the nanny's variable switches off.
TRIM_THRESHOLD_BYTES = 64 << 20
_M_TRIM_THRESHOLD = -1  # glibc's mallopt parameters (malloc.h)
_M_MMAP_THRESHOLD = -3
_M_MMAP_MAX = -4
#: Heap top kept by :func:`keep_large_arrays` (never trimmed in practice).
_NEVER_TRIM_BYTES = 2**31 - 1

_LOCK = threading.Lock()
_DONE: list[bool] = []
_LARGE: list[bool] = []


def _mallopt() -> ctypes._CFuncPtr | None:
    """glibc's ``mallopt``, or None where the C library is not glibc."""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return None
    if not hasattr(libc, "gnu_get_libc_version"):
        return None
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    return mallopt


def keep_freed_heap() -> bool:
    """Raise glibc's mmap and trim thresholds in this process (once); True if applied."""
    with _LOCK:
        if _DONE:
            return _DONE[0]
        mallopt = _mallopt()
        ok = mallopt is not None \
            and bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)) \
            and bool(mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES))
        _DONE.append(ok)
        return ok


def keep_large_arrays() -> bool:
    """Serve every allocation from the heap and never trim it (once per process).

    An augmented 5000² RGB pair allocates ≈ 0.8 GB of fresh large arrays (warped image
    and mask, warp fields, photometric output). Above glibc's 32 MiB mmap cap each is its
    own mapping, unmapped when freed, so every output pays a page fault and a page
    zeroing per page again: ``sys`` 0.26–0.28 s per pair in-process, 0.06–0.07 s with
    this, at the same peak resident memory (841 vs 845 MB over 10 pairs;
    docs/augmentation.md). The heap keeps its peak, which the next output needs anyway.
    Only the main arena obeys this: a Dask worker's executor thread still maps large
    arrays unless the process was started with ``MALLOC_ARENA_MAX=1``.

    Returns
    -------
    bool
        Whether glibc accepted the settings (False elsewhere, where nothing changes).
    """
    with _LOCK:
        if _LARGE:
            return _LARGE[0]
    keep_freed_heap()  # its one-time settings first: it must not undo these later
    with _LOCK:
        mallopt = _mallopt()
        ok = mallopt is not None and bool(mallopt(_M_MMAP_MAX, 0)) \
            and bool(mallopt(_M_TRIM_THRESHOLD, _NEVER_TRIM_BYTES))
        _LARGE.append(ok)
        return ok
