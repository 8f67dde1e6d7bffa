"""Programs from Debian's packages that tests drive: found on PATH, else a failure in CI and a skip elsewhere."""

from __future__ import annotations

import os
import shutil

import pytest


def require_tool(name: str, package: str) -> str:
    """The path of program ``name``; without it, fail in CI (``.ci/run`` installs ``package``) or skip the test."""
    path = shutil.which(name)
    if path is None:
        why = f"{name} is not installed (Debian: apt-get install {package})"
        if os.environ.get("CI"):
            pytest.fail(why + "; .ci/run installs it and CI never skips it")
        pytest.skip(why)
    return path
