"""Fixtures of the acquisition tests."""

from __future__ import annotations

from pathlib import Path
import gc
from collections.abc import Iterator
from typing import Any, Callable

import pytest

from acquire.runner import ScanRequest
from acquire_helpers import small_request


@pytest.fixture
def request_factory(tmp_path: Path) -> Callable[..., ScanRequest]:
    """Make small scan requests writing into the test's temporary folder."""
    def make(name: str = "scan.h5", **kw: Any) -> ScanRequest:
        return small_request(tmp_path / name, **kw)
    return make


@pytest.fixture(scope="module", autouse=True)
def _stop_sim_twins() -> Iterator[None]:
    """After each module: stop the in-process GCS twins and collect garbage now. CPython 3.11.7's
    ast.parse fails with 'AST constructor recursion depth mismatch' when a finalizer runs Python code in
    the middle of it (gh-106905, fixed in 3.11.8); left-over asyncio objects would otherwise be finalised
    during a later test such as the layering check."""
    yield
    from devices.twins.gcs import stop_sim_servers

    stop_sim_servers()
    gc.collect()
