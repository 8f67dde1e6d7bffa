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
