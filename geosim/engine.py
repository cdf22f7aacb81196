"""Where per-window, per-tile and per-flight tasks run.

A step is a plan (which outputs, from which inputs) plus tasks; each task reads its
inputs, computes and writes its own output atomically, and returns a small record.
Steps hand their tasks to :func:`parallel_map`, which runs them on the active engine:
in this process by default, or on a Dask cluster when one is active (see
:func:`using`). The driver only gathers the small records, in task order, so the
outputs are the same whatever ran them.

Task functions must be importable top-level functions and their arguments and results
picklable, so that they can be sent to worker processes.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from typing import Any, Protocol, TypeVar

T = TypeVar("T")
R = TypeVar("R")


class Engine(Protocol):
    """Runs independent tasks and returns their results in task order."""

    def map(self, fn: Callable[[T], R], items: Iterable[T]) -> list[R]:
        """``[fn(item) for item in items]``, possibly in parallel."""
        ...

    def describe(self) -> dict[str, Any]:
        """What ran the tasks, for ``run.json`` (kind, number of workers, address)."""
        ...


class InProcess:
    """Runs every task in this process, one after the other."""

    def map(self, fn: Callable[[T], R], items: Iterable[T]) -> list[R]:
        return [fn(item) for item in items]

    def describe(self) -> dict[str, Any]:
        return {"kind": "in-process", "workers": 1}


_ACTIVE: ContextVar[Engine | None] = ContextVar("geosim_engine", default=None)


def active() -> Engine:
    """The engine tasks run on now (in-process unless :func:`using` set another)."""
    return _ACTIVE.get() or InProcess()


@contextmanager
def using(engine: Engine) -> Iterator[Engine]:
    """Make ``engine`` the active engine inside the ``with`` block."""
    token = _ACTIVE.set(engine)
    try:
        yield engine
    finally:
        _ACTIVE.reset(token)


def parallel_map(fn: Callable[[T], R], items: Iterable[T]) -> list[R]:
    """Run ``fn`` on every item on the active engine; results in item order."""
    return active().map(fn, items)
