"""Kernels compiled on first use after installation, as a test makes numba do it on purpose."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any


def compiling_first(work: Callable[..., Any]) -> Callable[..., Any]:
    """``work`` that first makes numba compile a few new functions (each one new, so never from its cache), as the
    first calibration or reconstruction after installation does."""
    import numba

    def compiled_then_work(*args: Any, **kwargs: Any) -> Any:
        for k in range(6):
            numba.njit(lambda x, k=k: x * 2.0 + k)(1.0)
        return work(*args, **kwargs)

    return compiled_then_work
