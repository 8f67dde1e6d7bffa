"""Kernels compiled on first use after installation, as a test makes numba do it on purpose."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any


def compiling_first(work: Callable[..., Any], seconds: float = 0.0) -> Callable[..., Any]:
    """``work`` that first makes numba compile new functions (each one new, so never from its cache), six and
    for at least ``seconds``, as the first calibration or reconstruction after installation does."""
    import time

    import numba

    def compiled_then_work(*args: Any, **kwargs: Any) -> Any:
        start, k = time.perf_counter(), 0
        while k < 6 or time.perf_counter() - start < seconds:
            numba.njit(lambda x, k=k: x * 2.0 + k)(1.0)
            k += 1
        return work(*args, **kwargs)

    return compiled_then_work
