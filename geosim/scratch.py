"""Large scratch arrays reused from one tile to the next within a thread.

A freshly allocated array of tens of megabytes costs the kernel a page fault and a
page zeroing per page on first touch; for a 5000 px RGB tile the degrade step
touched ≈ 0.4 GB of new memory (decoded tile, mask, pyramid levels), ≈ 0.04–0.10 s
of system time per tile, up to a fifth of its CPU (benchmarks/bench_degrade_command.py,
docs/degradation.md). Buffers kept from the previous tile of the same size are
already mapped.

Rules for callers: a ``key`` belongs to one call site; what it returns is valid only
until the next :func:`scratch_array` call with that key in the same thread, so it must
never be returned to code that keeps it. The pool holds one array per key and thread
(the largest tile seen replaces a smaller one); :func:`release_scratch` empties it.
"""

from __future__ import annotations

import threading

import numpy as np

_LOCAL = threading.local()


def _pool() -> dict[str, np.ndarray]:
    pool = getattr(_LOCAL, "pool", None)
    if pool is None:
        pool = _LOCAL.pool = {}
    return pool


def scratch_array(key: str, shape: tuple[int, ...], dtype: np.dtype | type | str
                  ) -> np.ndarray:
    """An uninitialised C-contiguous array of ``shape`` and ``dtype``, reused per ``key``.

    Parameters
    ----------
    key
        Name of the call site's buffer (e.g. ``"degrade.level1"``).
    shape, dtype
        Shape and data type wanted; the pooled array is reused when it holds at least as
        many bytes (a view of its start is returned), else replaced.
    """
    dt = np.dtype(dtype)
    nbytes = int(np.prod(shape, dtype=np.int64)) * dt.itemsize
    pool = _pool()
    buf = pool.get(key)
    if buf is None or buf.nbytes < nbytes:
        pool.pop(key, None)  # let the old one go before allocating the larger one
        buf = pool[key] = np.empty(max(nbytes, 1), np.uint8)
    return buf[:nbytes].view(dt).reshape(shape)


def scratch_nbytes() -> int:
    """Bytes held by this thread's pool."""
    return sum(b.nbytes for b in _pool().values())


def release_scratch() -> None:
    """Drop this thread's pooled arrays (their memory is freed once unreferenced)."""
    _pool().clear()
