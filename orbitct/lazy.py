"""Package attributes imported when first used, so that importing a package's light parts (its options, its
errors) does not load its numerical kernels (numba, SciPy): ``orbitct --help`` and the options models stay quick."""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping
from typing import Any


def lazy_attributes(package: str, homes: Mapping[str, str]) -> Callable[[str], Any]:
    """A module ``__getattr__`` for ``package`` that imports each name in ``homes`` from its module on first use."""

    def __getattr__(name: str) -> Any:
        home = homes.get(name)
        if home is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(home), name)
        setattr(importlib.import_module(package), name, value)  # found directly from now on
        return value

    return __getattr__


__all__ = ["lazy_attributes"]
