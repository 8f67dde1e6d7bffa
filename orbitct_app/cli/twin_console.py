"""Serve one twin until Ctrl-C, with a console on stdin for hazards and faults (every ``orbitct twin`` command)."""

from __future__ import annotations

import asyncio
import sys
import threading
from collections.abc import Callable
from typing import Any

import click

from orbitct_app.cli.failure import Failure

CONSOLE_HELP = "console: 'latency MS', 'drop [N]', 'garble [N]', 'error [N]', 'missing [N]', 'match TEXT|-'"


def fault_command(faults: Any, words: list[str]) -> str | None:
    """Apply one console fault command to a twin's :class:`~devices.twins.runtime.TwinFaults`; what it did, or None."""
    if not words:
        return None
    if words[0] == "latency" and len(words) == 2:
        faults.latency_s = float(words[1]) / 1000.0
        return f"latency {faults.latency_s * 1000:g} ms"
    if words[0] == "match" and len(words) == 2:
        faults.match = "" if words[1] == "-" else words[1]
        return f"match {faults.match!r}"
    names = {"drop": "drop_next", "garble": "garble_next", "error": "error_next", "missing": "missing_frame_next"}
    if words[0] in names and len(words) <= 2:
        n = int(words[1]) if len(words) == 2 else 1
        setattr(faults, names[words[0]], n)
        return f"{words[0]} next {n}"
    return None


def serve_twin(
    twin: Any,
    host: str,
    port: int,
    banner: Callable[[int], str],
    *,
    console: bool | None = None,
    hazard: Callable[[list[str]], str | None] | None = None,
    after_start: Callable[[], str | None] | None = None,
) -> None:
    """Start ``twin`` on ``host:port``, print ``banner(bound_port)``, serve until Ctrl-C; optional stdin console.

    ``after_start`` runs in the twin's loop once it listens; a line it returns is printed.
    """
    use_console = sys.stdin.isatty() if console is None else console

    def handle(line: str) -> None:
        words = line.split()
        try:
            done = (hazard(words) if hazard else None) or fault_command(twin.faults, words)
        except ValueError as exc:
            done, err = None, str(exc)
        else:
            err = ""
        if words:
            click.echo(done or f"not understood ({err or line.strip()!r}); {CONSOLE_HELP}", err=True)

    async def main() -> None:
        loop = asyncio.get_running_loop()
        try:
            bound = await twin.start(host, port)
        except OSError as exc:
            raise Failure(
                f"cannot listen on {host}:{port} ({exc.strerror or exc})",
                "unavailable",
                "choose another --port, or stop the program that listens there",
            ) from None
        click.echo(banner(bound) + "; Ctrl-C stops", err=True)
        if after_start is not None:
            line = after_start()
            if line:
                click.echo(line, err=True)
        if use_console:

            def read_stdin() -> None:
                for line in sys.stdin:
                    loop.call_soon_threadsafe(handle, line)

            threading.Thread(target=read_stdin, name="twin-console", daemon=True).start()
        try:
            await asyncio.Event().wait()
        finally:
            await twin.stop()

    try:
        asyncio.run(main())
    except KeyboardInterrupt:
        click.echo("stopped", err=True)
