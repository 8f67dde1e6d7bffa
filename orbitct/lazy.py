"""Package attributes imported when first used, so that importing a package's light parts (its options, its
errors) does not load its numerical kernels (numba, SciPy): ``orbitct --help`` and the options models stay quick.

A name may be the same as a submodule's (``recon.fdk`` the function, in ``recon/fdk.py``). Importing a submodule
binds its name on the package, so such a binding is declined: the package's name stays what the package exports,
as it was when the package imported everything at once.
"""

from __future__ import annotations

import importlib
import sys
import types
from collections.abc import Mapping
from typing import Any, ClassVar


class _LazyPackage(types.ModuleType):
    """A package whose names in ``homes`` are imported from their modules on first use."""

    homes: ClassVar[Mapping[str, str]] = {}

    def __getattr__(self, name: str) -> Any:
        home = type(self).homes.get(name)
        if home is None:
            raise AttributeError(f"module {self.__name__!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(home), name)
        types.ModuleType.__setattr__(self, name, value)  # found directly from now on
        return value

    def __setattr__(self, name: str, value: Any) -> None:
        if isinstance(value, types.ModuleType) and name in type(self).homes:
            return  # a submodule of the same name as an exported function: the function keeps the name
        super().__setattr__(name, value)


def make_lazy(package: str, homes: Mapping[str, str]) -> None:
    """Make ``package`` (being imported) import each name in ``homes`` from its module on first use."""
    module = sys.modules[package]
    module.__class__ = type("LazyPackage", (_LazyPackage,), {"homes": dict(homes)})
    for name in homes:  # a same-named submodule imported before this call
        if isinstance(module.__dict__.get(name), types.ModuleType):
            del module.__dict__[name]


__all__ = ["make_lazy"]
