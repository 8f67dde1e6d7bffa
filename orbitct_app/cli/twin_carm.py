"""``orbitct twin carm``: the robotic C-arm twin (navigation points + flat panel) standalone until Ctrl-C."""

from __future__ import annotations

import click

from orbitct_app.cli.twin_console import serve_twin
from orbitct_app.cli.values import FiniteFloat


@click.command("carm")
@click.option("--host", default="127.0.0.1", show_default=True, help="Interface to listen on.")
@click.option(
    "--port", type=click.IntRange(0, 65535), default=5040, show_default=True, help="TCP port (0 = any free port)."
)
@click.option(
    "--detector-size",
    "rows",
    type=click.IntRange(8, 4096),
    default=256,
    show_default=True,
    help="Panel pixels per side (427 mm panel).",
)
@click.option("--phantom", default="B", show_default=True, help="Experiment phantom the C-arm images (A, B or C).")
@click.option(
    "--primary-range-deg",
    nargs=2,
    type=FiniteFloat(),
    default=(-185.0, 185.0),
    show_default=True,
    help="LAO/RAO range.",
)
@click.option(
    "--secondary-range-deg",
    nargs=2,
    type=FiniteFloat(),
    default=(-50.0, 50.0),
    show_default=True,
    help="CRAN/CAUD range.",
)
@click.option(
    "--max-step-deg",
    type=FiniteFloat(min=0, min_open=True),
    default=5.0,
    show_default=True,
    help="Largest step between points.",
)
@click.option(
    "--max-speed-deg-s",
    type=FiniteFloat(min=0, min_open=True),
    default=30.0,
    show_default=True,
    help="Top angular speed.",
)
@click.option(
    "--sag-deg",
    type=FiniteFloat(),
    default=0.8,
    show_default=True,
    help="Tilt sag amplitude (true tilt = tilt - sag cos(primary) cos(tilt)).",
)
@click.option("--drift-mm", type=FiniteFloat(), default=2.0, show_default=True, help="Isocenter drift amplitude.")
@click.option("--eta-deg", type=FiniteFloat(), default=0.5, show_default=True, help="In-plane panel rotation.")
@click.option(
    "--primary-offset-deg", type=FiniteFloat(), default=0.3, show_default=True, help="Offset of the true primary angle."
)
@click.option(
    "--time-scale",
    type=FiniteFloat(min=0, min_open=True),
    default=1.0,
    show_default=True,
    help="Simulated seconds per real second (10 = moves ten times faster).",
)
@click.option("--latency-ms", type=FiniteFloat(0), default=0.0, help="Delay added before every reply.")
@click.option(
    "--console/--no-console",
    default=None,
    help="Read hazard/fault commands from stdin (default: when stdin is a terminal).",
)
def carm(
    host: str,
    port: int,
    rows: int,
    phantom: str,
    primary_range_deg: tuple[float, float],
    secondary_range_deg: tuple[float, float],
    max_step_deg: float,
    max_speed_deg_s: float,
    sag_deg: float,
    drift_mm: float,
    eta_deg: float,
    primary_offset_deg: float,
    time_scale: float,
    latency_ms: float,
    console: bool | None,
) -> None:
    """Serve the simulated C-arm: load navigation programs, move, play them back and stream frames.

    Console commands (one a line): stuck on|off, latency MS, drop [N], garble [N], error [N],
    missing [N], match TEXT|-.
    """
    from devices.carm_program import CArmLimits
    from devices.twins.carm import CArmTwin

    for name, (lo, hi) in (("--primary-range-deg", primary_range_deg), ("--secondary-range-deg", secondary_range_deg)):
        if not lo < hi:
            raise click.BadParameter(f"low ({lo:g}) must be below high ({hi:g})", param_hint=name)
    limits = CArmLimits(primary_range_deg, secondary_range_deg, max_step_deg, max_speed_deg_s)

    twin = CArmTwin(
        limits=limits,
        rows=rows,
        phantom=phantom,
        sag_deg=sag_deg,
        drift_mm=drift_mm,
        eta_deg=eta_deg,
        primary_offset_deg=primary_offset_deg,
        time_scale=time_scale,
    )
    twin.faults.latency_s = latency_ms / 1000.0

    def hazard(words: list[str]) -> str | None:
        if words[:1] == ["stuck"] and words[1:2] in (["on"], ["off"]):
            twin.stuck = words[1] == "on"
            return f"stuck {words[1]}"
        return None

    banner = f"C-arm twin listening on tcp://{host}:{{}} ({rows}x{rows} panel, phantom {phantom})"
    serve_twin(twin, host, port, banner.format, console=console, hazard=hazard)
