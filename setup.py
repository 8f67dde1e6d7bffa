"""Build hook: the wheel and the sdist carry every runtime asset, the volume viewer's included.

The viewer's library (niivue) is too large to keep in the repository; ``orbitct_app/console/assets.py`` fetches the
pinned file and checks its SHA-256. Building a wheel or an sdist runs it first, so a package built from a clean
checkout serves the 3-D viewer. Offline, copy the file to ``orbitct_app/console/static/vendor/`` before building.
Everything else about the package is in ``pyproject.toml``.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py
from setuptools.command.sdist import sdist

HERE = Path(__file__).resolve().parent


def fetch_console_assets() -> None:
    """Run the console's asset fetcher (loaded by path: the package itself is not importable while it builds)."""
    spec = importlib.util.spec_from_file_location("_orbitct_assets", HERE / "orbitct_app" / "console" / "assets.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    module.fetch()


class BuildPyWithAssets(build_py):
    """``build_py`` that fetches the console's assets first."""

    def run(self) -> None:
        fetch_console_assets()
        super().run()


class SdistWithAssets(sdist):
    """``sdist`` that fetches the console's assets first."""

    def run(self) -> None:
        fetch_console_assets()
        super().run()


setup(cmdclass={"build_py": BuildPyWithAssets, "sdist": SdistWithAssets})
