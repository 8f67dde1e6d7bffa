"""Bounds whose measured values are kept: ``below("err_px", err, 0.3)`` asserts and, where the environment
variable ORBITCT_TEST_MEASURES names a file, appends the value to it. ``benchmarks/suite_stability.py`` reads
them back to give each bound's margin over the spread between machines, thread counts and load."""

from __future__ import annotations

import json
import os

MEASURES_ENV = "ORBITCT_TEST_MEASURES"


def below(name: str, value: float, bound: float) -> None:
    """Assert ``value < bound``, recording both (with the running test's id) where measures are collected."""
    path = os.environ.get(MEASURES_ENV)
    if path:
        test = os.environ.get("PYTEST_CURRENT_TEST", "?").rsplit(" (", 1)[0]
        with open(path, "a", encoding="utf-8") as out:
            out.write(json.dumps({"test": test, "name": name, "value": float(value), "bound": float(bound)}) + "\n")
    assert value < bound, f"{name} = {value:.4g}, bound {bound:.4g}"
