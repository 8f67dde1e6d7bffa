"""``orbitct twin xray``: the X-ray generator twin (Modbus TCP) standalone until Ctrl-C."""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from typing import Any

import click


@click.command("xray")
@click.option("--host", default="127.0.0.1", show_default=True, help="Interface to listen on.")
@click.option("--port", type=click.IntRange(0, 65535), default=5020, show_default=True, help="TCP port (0 = any free port).")
@click.option("--prep-ms", type=click.IntRange(0, 60000), default=200, show_default=True, help="Time from PREP to READY.")
@click.option("--door-open", is_flag=True, help="Start with the door interlock open.")
@click.option("--fault", type=click.IntRange(0, 4), default=0, help="Start in FAULT with this fault code (3 = generator).")
@click.option("--latency-ms", type=click.FloatRange(0), default=0.0, help="Delay added before every reply.")
def xray(host: str, port: int, prep_ms: int, door_open: bool, fault: int, latency_ms: float) -> None:
    """Serve the simulated X-ray generator's register map over Modbus TCP."""
    from devices.twins.xray import XrayTwin
    from devices.xray_registers import FaultCode, GeneratorState

    twin = XrayTwin(prep_s=prep_ms / 1000.0)
    twin.faults.latency_s = latency_ms / 1000.0
    if door_open:
        twin.door_closed = False
    if fault:
        twin.state, twin.fault_code = GeneratorState.FAULT, FaultCode(fault)
    serve_twin(twin, host, port, lambda bound: f"X-ray generator twin listening on modbus://{host}:{bound} (device id 1)")


def serve_twin(twin: Any, host: str, port: int, banner: Callable[[int], str]) -> None:
    """Start ``twin`` on ``host:port``, print ``banner(bound_port)`` to stderr, serve until Ctrl-C."""

    async def main() -> None:
        bound = await twin.start(host, port)
        click.echo(banner(bound) + "; Ctrl-C stops", err=True)
        try:
            await asyncio.Event().wait()
        finally:
            await twin.stop()

    try:
        asyncio.run(main())
    except KeyboardInterrupt:
        click.echo("stopped", err=True)
