"""Headless Chromium (Debian's package) driven by Playwright, for the web console's tests."""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import pytest

from tests.helpers.tools import require_tool

# The flags a closed lab network needs (no background connections) and software WebGL2 for the volume viewer.
CHROMIUM_ARGS = [
    "--headless=new",
    "--no-sandbox",
    "--disable-gpu",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--disable-quic",
    "--enable-unsafe-swiftshader",
    "--use-angle=swiftshader",
]


def chromium_path() -> str:
    """The Chromium executable (``ORBITCT_CHROMIUM``, else Debian's ``chromium``); fails in CI, skips elsewhere."""
    return os.environ.get("ORBITCT_CHROMIUM") or require_tool("chromium", "chromium")


@contextmanager
def chromium() -> Iterator[Any]:
    """A Playwright browser on Debian's Chromium (no browser download)."""
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:  # the test extra installs it
        pytest.fail("playwright is not installed: pip install -e '.[test]'")
    path = chromium_path()
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=path, args=CHROMIUM_ARGS)
        try:
            yield browser
        finally:
            browser.close()
