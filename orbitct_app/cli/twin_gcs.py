"""``orbitct twin hexapod`` and ``orbitct twin rotation-stage``: a GCS 2.0 controller twin on a real socket.

Console commands (one a line): ``stuck AXIS on|off`` and the fault commands every twin console takes.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import click

from orbitct_app.cli.twin_console import serve_twin
from orbitct_app.cli.values import SEED, FiniteFloat


def _options(fn: Callable[..., Any]) -> Callable[..., Any]:
    decorators = [
        click.option("--host", default="127.0.0.1", show_default=True, help="Address to listen on."),
        click.option(
            "--port",
            type=click.IntRange(0, 65535),
            default=50000,
            show_default=True,
            help="TCP port (PI controllers use 50000; 0 = any free port).",
        ),
        click.option("--serial", "serial_pty", is_flag=True, help="Also serve on a pseudo-terminal (prints its path)."),
        click.option(
            "--time-scale",
            type=FiniteFloat(min=0.001),
            default=1.0,
            show_default=True,
            help="Run motion this many times faster than real.",
        ),
        click.option("--perfect", is_flag=True, help="No hidden mechanical errors (read-back = true pose)."),
        click.option("--seed", type=SEED, default=None, help="Seed of the hidden mechanical errors."),
        click.option("--latency-ms", type=FiniteFloat(min=0.0), default=0.0, help="Fault: delay every reply."),
        click.option(
            "--drop-next",
            type=click.IntRange(min=0),
            default=0,
            help="Fault: drop the connection at each of the next N commands.",
        ),
        click.option("--garble-next", type=click.IntRange(min=0), default=0, help="Fault: garble the next N replies."),
        click.option(
            "--error",
            "errors",
            multiple=True,
            metavar="CODE:COMMAND",
            help="Fault: the next COMMAND fails with GCS error CODE (e.g. 7:MOV); repeatable.",
        ),
        click.option(
            "--stuck-axis",
            "stuck",
            multiple=True,
            metavar="AXIS",
            help="Fault: AXIS never moves (never on target); repeatable.",
        ),
        click.option(
            "--console/--no-console",
            default=None,
            help="Read hazard/fault commands from stdin (default: when stdin is a terminal).",
        ),
    ]
    for deco in reversed(decorators):
        fn = deco(fn)
    return fn


def _run(
    kind: str,
    host: str,
    port: int,
    serial_pty: bool,
    time_scale: float,
    perfect: bool,
    seed: int | None,
    latency_ms: float,
    drop_next: int,
    garble_next: int,
    errors: tuple[str, ...],
    stuck: tuple[str, ...],
    console: bool | None,
) -> None:
    from devices.twins.gcs import GcsTwin, make_controller

    options: dict[str, Any] = {"time_scale": time_scale, "imperfect": not perfect}
    if seed is not None:
        options["seed"] = seed
    controller = make_controller(kind, **options)
    twin = GcsTwin(controller)
    _apply_faults(twin, latency_ms, drop_next, garble_next, errors, stuck)

    def hazard(words: list[str]) -> str | None:
        if words[:1] == ["stuck"] and len(words) == 3 and words[1] in controller.axes and words[2] in ("on", "off"):
            controller.stick(words[1], words[2] == "on")
            return f"axis {words[1]} stuck {words[2]}"
        return None

    def serial() -> str | None:
        return f"serial: serial://{twin.open_serial()}?baud=115200" if serial_pty else None

    banner = f"{kind} twin listening on tcp://{host}:{{}} (axes {' '.join(controller.axes)})"
    serve_twin(twin, host, port, banner.format, console=console, hazard=hazard, after_start=serial)


def _apply_faults(
    twin: Any, latency_ms: float, drop_next: int, garble_next: int, errors: tuple[str, ...], stuck: tuple[str, ...]
) -> None:
    faults = twin.faults
    faults.latency_s, faults.drop_next, faults.garble_next = latency_ms / 1000.0, drop_next, garble_next
    for spec in errors:
        code, sep, command = spec.partition(":")
        if not sep or not code.strip().isdigit() or not command.strip():
            raise click.BadParameter(f"{spec!r}: expected CODE:COMMAND, e.g. 7:MOV", param_hint="--error")
        faults.add_error(int(code), command.strip())
    for axis in stuck:
        if axis not in twin.controller.axes:
            raise click.BadParameter(f"{axis!r}: axes are {', '.join(twin.controller.axes)}", param_hint="--stuck-axis")
        twin.controller.stick(axis)


@click.command("hexapod")
@_options
def hexapod(**kwargs: Any) -> None:
    """Hexapod twin (C-887 style; GCS 2.0 over TCP, PIPython-compatible)."""
    _run("hexapod", **kwargs)


@click.command("rotation-stage")
@_options
def rotation_stage(**kwargs: Any) -> None:
    """Rotation-stage twin (one axis '1' in degrees; GCS 2.0 over TCP)."""
    _run("rotation_stage", **kwargs)
