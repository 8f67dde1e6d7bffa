"""Progress events that long operations report, whoever listens (terminal bar, REST stream)."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field


@dataclass(frozen=True)
class ProgressEvent:
    """``done`` of ``total`` steps of ``stage``, with optional metrics (rate, RPE, cost, ...)."""

    stage: str
    done: int
    total: int
    message: str = ""
    metrics: Mapping[str, float] = field(default_factory=dict)


ProgressCallback = Callable[[ProgressEvent], None]


def report(
    callback: ProgressCallback | None, stage: str, done: int, total: int, message: str = "", **metrics: float
) -> None:
    """Send one event to ``callback`` if there is one."""
    if callback is not None:
        callback(ProgressEvent(stage, done, total, message, metrics))


def report_expected(
    callback: ProgressCallback | None, what: str, seconds: float, *, at_most: bool = False, where: str = "machine"
) -> None:
    """Say how long ``what`` is expected to take in all (stage ``duration``, metric ``expected_s``): a line in a
    terminal, the ``expected_s`` of a job's record in the service."""
    bound = "at most " if at_most else ""
    report(
        callback,
        "duration",
        1,
        1,
        f"{what} takes {bound}about {describe_seconds(seconds)} on this {where} now",
        expected_s=float(seconds),
    )


def describe_seconds(seconds: float) -> str:
    """A duration as a person reads it: '40 s', '12 min', '3.5 h'."""
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 5400:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"
