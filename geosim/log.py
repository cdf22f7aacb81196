"""Logging and progress bars of the library, configured by the CLI (``-v`` / ``-q``).

The library logs to the ``geosim`` logger and never prints; an application decides where
messages go. :func:`configure` is what ``geosim`` uses: messages on stderr, INFO by
default, DEBUG with ``-v``, only warnings and errors with ``-q`` (which also hides the
progress bars).
"""

from __future__ import annotations

import logging
import sys
from collections.abc import Callable

LOGGER_NAME = "geosim"


def get_logger(name: str = LOGGER_NAME) -> logging.Logger:
    """The package logger or one of its children (``geosim.deliver`` …)."""
    return logging.getLogger(name)


def info(message: str) -> None:
    """Log one INFO line on the package logger (a drop-in for the old ``echo`` callbacks)."""
    logging.getLogger(LOGGER_NAME).info(message)


def configure(*, verbose: int = 0, quiet: bool = False) -> Callable[[], None]:
    """Send the ``geosim`` logger to stderr at the level the flags ask for.

    Parameters
    ----------
    verbose
        0: INFO; 1 or more: DEBUG with logger names.
    quiet
        Only WARNING and above, and progress bars off (wins over ``verbose``).

    Returns
    -------
    callable
        Undoes the configuration (handlers and the progress-bar switch).
    """
    logger = logging.getLogger(LOGGER_NAME)
    level = logging.WARNING if quiet else (logging.DEBUG if verbose else logging.INFO)
    handler = logging.StreamHandler(sys.stderr)
    fmt = "%(levelname)s %(name)s: %(message)s" if verbose and not quiet else "%(message)s"
    handler.setFormatter(logging.Formatter(fmt))
    saved = (list(logger.handlers), logger.level, logger.propagate)
    logger.handlers = [handler]
    logger.setLevel(level)
    logger.propagate = False
    undo_progress = silence_progress() if quiet else (lambda: None)

    def undo() -> None:
        logger.handlers, lvl, logger.propagate = saved[0], saved[1], saved[2]
        logger.setLevel(lvl)
        undo_progress()

    return undo


def silence_progress() -> Callable[[], None]:
    """Turn every tqdm progress bar off (the steps create theirs with ``disable=None``)."""
    import tqdm

    original = tqdm.tqdm.__dict__["__init__"]   # the descriptor itself, restored as it was

    def init(self, *args, **kwargs):  # type: ignore[no-untyped-def]
        kwargs["disable"] = True
        original.__get__(self, type(self))(*args, **kwargs)

    tqdm.tqdm.__init__ = init  # type: ignore[method-assign]

    def undo() -> None:
        tqdm.tqdm.__init__ = original  # type: ignore[method-assign]

    return undo


__all__ = ["configure", "get_logger", "info", "silence_progress"]
