"""Compilation time is measured apart, so that reported timings never include it."""

from __future__ import annotations

import numba
import numpy as np

from orbitct.compiletime import CompileClock


def test_compiling_is_counted_and_running_compiled_code_is_not() -> None:
    @numba.njit(cache=False)
    def total(a: np.ndarray) -> float:
        s = 0.0
        for x in a:
            s += x
        return s

    with CompileClock() as clock:
        assert clock.seconds == 0.0
        total(np.arange(10.0))
        first = clock.seconds
        assert first > 0.0
        total(np.arange(1000.0))  # compiled already: no compile time added
        assert clock.seconds == first
    total(np.arange(10, dtype=np.int64))  # after the block: not counted
    assert clock.seconds == first
