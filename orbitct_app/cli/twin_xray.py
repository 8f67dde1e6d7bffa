"""``orbitct twin xray``: the X-ray generator twin (Modbus TCP) standalone until Ctrl-C."""

from __future__ import annotations

import asyncio
import sys
import threading
from collections.abc import Callable
from typing import Any

import click


CONSOLE_HELP = (
    "console: 'latency MS', 'drop [N]', 'garble [N]', 'error [N]', 'missing [N]', 'match TEXT|-'"
)


@click.command("xray")
@click.option("--host", default="127.0.0.1", show_default=True, help="Interface to listen on.")
@click.option("--port", type=click.IntRange(0, 65535), default=5020, show_default=True, help="TCP port (0 = any free port).")
@click.option("--prep-ms", type=click.IntRange(0, 60000), default=200, show_default=True, help="Time from PREP to READY.")
@click.option("--door-open", is_flag=True, help="Start with the door interlock open.")
@click.option("--fault", type=click.IntRange(0, 4), default=0, help="Start in FAULT with this fault code (3 = generator).")
@click.option("--latency-ms", type=click.FloatRange(0), default=0.0, help="Delay added before every reply.")
@click.option("--console/--no-console", default=None, help="Read hazard/fault commands from stdin (default: when stdin is a terminal).")
def xray(host: str, port: int, prep_ms: int, door_open: bool, fault: int, latency_ms: float, console: bool | None) -> None:
    """Serve the simulated X-ray generator's register map over Modbus TCP.

    Console commands (one a line): door open|closed, fault CODE, heartbeat freeze|run, and the
    fault commands every twin takes: latency MS, drop [N], garble [N], error [N], missing [N], match TEXT|-.
    """
    from devices.twins.xray import XrayTwin
    from devices.xray_registers import FaultCode, GeneratorState

    twin = XrayTwin(prep_s=prep_ms / 1000.0)
    twin.faults.latency_s = latency_ms / 1000.0
    if door_open:
        twin.door_closed = False
    if fault:
        twin.state, twin.fault_code = GeneratorState.FAULT, FaultCode(fault)

    def hazard(words: list[str]) -> str | None:
        if words[:1] == ["door"] and words[1:2] in (["open"], ["closed"]):
            twin.set_door(words[1] == "closed")
            return f"door {words[1]}"
        if words[:1] == ["fault"] and len(words) == 2 and words[1].isdigit() and int(words[1]) in FaultCode._value2member_map_:
            twin.raise_fault(FaultCode(int(words[1])))
            return f"fault {FaultCode(int(words[1])).name}"
        if words[:1] == ["heartbeat"] and words[1:2] in (["freeze"], ["run"]):
            twin.heartbeat_frozen = words[1] == "freeze"
            return f"heartbeat {words[1]}"
        return None

    banner = f"X-ray generator twin listening on modbus://{host}:{{}} (device id 1)"
    serve_twin(twin, host, port, banner.format, console=console, hazard=hazard)


def fault_command(faults: Any, words: list[str]) -> str | None:
    """Apply one console fault command to a :class:`~devices.twins.xray.TwinFaults`; what it did, or None."""
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
) -> None:
    """Start ``twin`` on ``host:port``, print ``banner(bound_port)``, serve until Ctrl-C; optional stdin console."""
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
        bound = await twin.start(host, port)
        click.echo(banner(bound) + "; Ctrl-C stops", err=True)
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
