"""``orbitct twin xray``: the X-ray generator twin (Modbus TCP) standalone until Ctrl-C."""

from __future__ import annotations

import click

from orbitct_app.cli.twin_console import serve_twin
from orbitct_app.cli.values import FiniteFloat


@click.command("xray")
@click.option("--host", default="127.0.0.1", show_default=True, help="Interface to listen on.")
@click.option(
    "--port", type=click.IntRange(0, 65535), default=5020, show_default=True, help="TCP port (0 = any free port)."
)
@click.option(
    "--prep-ms", type=click.IntRange(0, 60000), default=200, show_default=True, help="Time from PREP to READY."
)
@click.option("--door-open", is_flag=True, help="Start with the door interlock open.")
@click.option(
    "--fault", type=click.IntRange(0, 4), default=0, help="Start in FAULT with this fault code (3 = generator)."
)
@click.option("--latency-ms", type=FiniteFloat(0), default=0.0, help="Delay added before every reply.")
@click.option(
    "--console/--no-console",
    default=None,
    help="Read hazard/fault commands from stdin (default: when stdin is a terminal).",
)
def xray(
    host: str, port: int, prep_ms: int, door_open: bool, fault: int, latency_ms: float, console: bool | None
) -> None:
    """Serve the simulated X-ray generator's register map over Modbus TCP.

    Console commands (one a line): door open|closed, fault CODE, heartbeat freeze|run, misanswer [N]
    (the next N register reads answered as the other kind of register read, as a faulty gateway), and the
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
        if (
            words[:1] == ["fault"]
            and len(words) == 2
            and words[1].isdigit()
            and int(words[1]) in FaultCode._value2member_map_
        ):
            twin.raise_fault(FaultCode(int(words[1])))
            return f"fault {FaultCode(int(words[1])).name}"
        if words[:1] == ["heartbeat"] and words[1:2] in (["freeze"], ["run"]):
            twin.heartbeat_frozen = words[1] == "freeze"
            return f"heartbeat {words[1]}"
        if words[:1] == ["misanswer"] and len(words) <= 2:
            twin.faults.misanswer_next = int(words[1]) if len(words) == 2 else 1  # ValueError: "not understood"
            return f"misanswer next {twin.faults.misanswer_next}"
        return None

    banner = f"X-ray generator twin listening on modbus://{host}:{{}} (device id 1)"
    serve_twin(twin, host, port, banner.format, console=console, hazard=hazard)
