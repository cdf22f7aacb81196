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

_LOCK = threading.Lock()
_DONE: list[bool] = []


def keep_freed_heap() -> bool:
    """Raise glibc's mmap and trim thresholds in this process (once); True if applied."""
    with _LOCK:
        if _DONE:
            return _DONE[0]
        ok = False
        try:
            libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
            mallopt = libc.mallopt
        except (OSError, AttributeError):
            mallopt = None
        if mallopt is not None and hasattr(libc, "gnu_get_libc_version"):
            mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
            ok = bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)) \
                and bool(mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES))
        _DONE.append(ok)
        return ok
