"""Fixtures of the acquisition tests."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from acquire.runner import ScanRequest
from tests.helpers.bench import small_request


@pytest.fixture
def request_factory(tmp_path: Path) -> Callable[..., ScanRequest]:
    """Make small scan requests writing into the test's temporary folder."""

    def make(name: str = "scan.h5", **kw: Any) -> ScanRequest:
        return small_request(tmp_path / name, **kw)

    return make
