"""How a command ends on bad input or a refused action: one line on stderr naming what is wrong, and an exit code."""

from __future__ import annotations

import sys
from typing import NoReturn

import click


def fail(message: str, code: int = 2) -> NoReturn:
    """Print ``error: message`` to stderr and exit with ``code`` (2: bad input or refused; 1: the action failed)."""
    click.echo(f"error: {message}", err=True)
    sys.exit(code)
