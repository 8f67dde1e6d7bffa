"""How a command ends on bad input, a refused action or a failure: ``error [code]: what happened; what to do`` on
stderr, and the exit status of the code (the catalogue, :mod:`orbitct_app.error_codes`)."""

from __future__ import annotations

import sys
from typing import IO, Any, NoReturn

import click

from orbitct_app.error_codes import code_for_exception, error_kind, sentence


class Failure(click.ClickException):
    """An error as the command's user reads it: one sentence with the catalogue's code and exit status."""

    def __init__(self, message: str, code: str = "invalid_parameters", advice: str | None = None) -> None:
        kind = error_kind(code)
        self.code = code
        self.advice = kind.advice if advice is None else advice
        super().__init__(sentence(message, self.advice))
        # the exit status follows the code, so it is the instance's (click reads it from the instance)
        self.exit_code = kind.exit_status if kind.exit_status is not None else 1  # type: ignore[misc]

    def show(self, file: IO[Any] | None = None) -> None:
        """Print ``error [code]: message`` to stderr (after SIGHUP the terminal may be gone: the exit status stays)."""
        try:
            click.echo(f"error [{self.code}]: {self.message}", err=True)
        except OSError:
            pass


def fail(
    message: str, code: str = "invalid_parameters", advice: str | None = None, exit_status: int | None = None
) -> NoReturn:
    """Print ``error [code]: message; advice`` to stderr and exit with the code's exit status (``exit_status``: a
    signal's own, 128 + its number), also from inside a ``try`` that catches ``Exception``."""
    failure = Failure(message, code, advice)
    failure.show()
    sys.exit(failure.exit_code if exit_status is None else exit_status)


def as_failure(exc: BaseException, ctx: click.Context | None = None) -> Failure:
    """Any error that ends a command, in the catalogue's terms: click's usage errors name the option and point to
    ``--help``; a file that cannot be read or written names the file; anything unexpected says so (no class name,
    no traceback; ``ORBITCT_DEBUG=1`` shows the traceback)."""
    if isinstance(exc, Failure):
        return exc
    if isinstance(exc, click.UsageError):
        where = exc.ctx.command_path if exc.ctx is not None else (ctx.command_path if ctx else "orbitct")
        command = " ".join(["orbitct", *where.split()[1:]])  # the program's name, however it was started
        return Failure(exc.format_message(), "invalid_parameters", f"see '{command} --help'")
    if isinstance(exc, click.ClickException):
        return Failure(exc.format_message(), "action_failed")
    if isinstance(exc, KeyboardInterrupt):
        return Failure("stopped by Ctrl-C", "interrupted")
    if isinstance(exc, click.Abort):  # a question answered with Ctrl-C or end of input
        return Failure("not confirmed: nothing was done", "action_failed", "run it again and answer the question")
    code = code_for_exception(exc)
    if isinstance(exc, MemoryError):
        return Failure("it ran out of memory", code, "make the work smaller or use a machine with more")
    if isinstance(exc, OSError) and code != "internal_error":
        where = f"{exc.filename}: " if exc.filename else ""
        return Failure(f"{where}{exc.strerror or exc}", code)
    text = str(exc).strip() or "no message"
    if code != "internal_error":  # orbitct's own errors (ScanFileError, CalibrationError, ...) say what was wrong
        return Failure(text, code)
    return Failure(
        f"an unexpected error stopped the command ({text})",
        "internal_error",
        "try again; if it fails again, report it with the command you ran (ORBITCT_DEBUG=1 shows the details)",
    )
