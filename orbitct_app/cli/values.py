"""Option types of the command line that refuse what Python's ``float`` and ``int`` let through: ``nan`` and
``inf`` where a number of something is meant, negative seeds."""

from __future__ import annotations

import math
from typing import Any

import click


class FiniteFloat(click.FloatRange):
    """A finite number within optional bounds (``nan`` and ``inf`` refused: they pass every comparison or none)."""

    name = "finite number"

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> Any:
        rv = super().convert(value, param, ctx)
        if isinstance(rv, float) and not math.isfinite(rv):
            self.fail(f"{value!r} is not a finite number", param, ctx)
        return rv

    def _describe_range(self) -> str:
        """No range in the help where there are no bounds (click wrote ``[x<=None]``)."""
        return "" if self.min is None and self.max is None else super()._describe_range()


#: a random seed: what numpy's generators take (0 to 2^32 - 1)
SEED = click.IntRange(0, 2**32 - 1)
