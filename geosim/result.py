"""What every pipeline step returns: :class:`StepResult`."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any


@dataclass
class StepResult:
    """The outcome of one pipeline step.

    Attributes
    ----------
    summary
        One line for people ("312 tile(s) degraded to 0.5 m at Q = 4.34 ...").
    warnings
        Things the user should know although the step succeeded; the CLI prints them
        and run.json records them.
    outputs
        Every file the step wrote, relative to the run folder (POSIX). run.json records
        them, so a rerun can remove the ones it no longer produces and never touches a
        file geosim did not write.
    record
        JSON-able numbers for run.json (``steps.<name>.summary``, beside ``text``).
    """

    summary: str
    warnings: list[str] = field(default_factory=list)
    outputs: list[str] = field(default_factory=list)
    record: dict[str, Any] = field(default_factory=dict)

    def summary_record(self) -> dict[str, Any]:
        """``steps.<name>.summary`` of run.json: the record plus ``text``."""
        return {**self.record, "text": self.summary}
