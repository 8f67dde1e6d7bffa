"""The quality verdict every calibration and reconstruction carries: passed, passed with warnings, or failed.

One verdict, shown alike everywhere (CLI exit status, REST job state, console, reports, scan files): ``reasons``
make it fail, ``warnings`` make it pass with warnings. In a scan file it is three attributes of the result's group
(:meth:`Verdict.attrs`), read back with :meth:`Verdict.from_attrs`.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

PASSED = "passed"
PASSED_WITH_WARNINGS = "passed_with_warnings"
FAILED = "failed"
#: the status values, and how a person reads them
LABELS = {PASSED: "passed", PASSED_WITH_WARNINGS: "passed with warnings", FAILED: "failed"}


@dataclass(frozen=True)
class Verdict:
    """Whether a result can be trusted: ``reasons`` it cannot (failed), ``warnings`` to read before using it."""

    reasons: tuple[str, ...] = ()
    warnings: tuple[str, ...] = ()

    @property
    def passed(self) -> bool:
        """No reason to distrust it (warnings allowed)."""
        return not self.reasons

    @property
    def status(self) -> str:
        """``passed``, ``passed_with_warnings`` or ``failed``."""
        if self.reasons:
            return FAILED
        return PASSED_WITH_WARNINGS if self.warnings else PASSED

    @property
    def label(self) -> str:
        """The status as a person reads it."""
        return LABELS[self.status]

    def sentence(self) -> str:
        """The verdict and its reasons (or warnings) in one line."""
        said = self.reasons or self.warnings
        return self.label + (": " + "; ".join(said) if said else "")

    def summary(self) -> dict[str, Any]:
        """JSON-ready: status, label, reasons, warnings."""
        return {
            "status": self.status,
            "label": self.label,
            "reasons": list(self.reasons),
            "warnings": list(self.warnings),
        }

    def attrs(self) -> dict[str, object]:
        """The attributes that store it in a scan file's result group."""
        return {
            "verdict": self.status,
            "verdict_reasons_json": json.dumps(list(self.reasons)),
            "verdict_warnings_json": json.dumps(list(self.warnings)),
        }

    @classmethod
    def from_attrs(cls, attrs: Mapping[str, Any]) -> Verdict | None:
        """The verdict stored by :meth:`attrs`, or None where the group has none (files written before it)."""
        if "verdict" not in attrs:
            return None

        def texts(key: str) -> tuple[str, ...]:
            try:
                return tuple(str(t) for t in json.loads(str(attrs.get(key, "[]"))))
            except ValueError:
                return ()

        reasons = texts("verdict_reasons_json")
        if str(attrs["verdict"]) == FAILED and not reasons:
            reasons = ("stored as failed without a reason",)
        return cls(reasons, texts("verdict_warnings_json"))


__all__ = ["FAILED", "LABELS", "PASSED", "PASSED_WITH_WARNINGS", "Verdict"]
