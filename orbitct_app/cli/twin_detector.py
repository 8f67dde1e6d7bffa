"""``orbitct twin detector``: the flat-panel twin standalone until Ctrl-C, imaging a bench of twins elsewhere."""

from __future__ import annotations

from pathlib import Path

import click

from orbitct_app.cli.failure import fail
from orbitct_app.cli.twin_console import serve_twin

_FOLLOWED = ("hexapod", "rotation_stage", "xray")


@click.command("detector")
@click.option("--host", default="127.0.0.1", show_default=True, help="Interface to listen on.")
@click.option(
    "--port", type=click.IntRange(0, 65535), default=5030, show_default=True, help="TCP port (0 = any free port)."
)
@click.option(
    "--config",
    "config_path",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="A bench configuration whose hexapod, rotation_stage and xray are tcp:// and modbus:// twins (or "
    "devices) elsewhere: the panel takes their pose and exposures, and the configuration's panel size, "
    "distances, phantom and stack. Without it the panel images its own unmoving phantom and takes "
    "frames on software triggers only.",
)
@click.option(
    "--console/--no-console", default=None, help="Read fault commands from stdin (default: when stdin is a terminal)."
)
def detector(host: str, port: int, config_path: Path | None, console: bool | None) -> None:
    """Serve the simulated flat panel (frame protocol over TCP).

    With --config it follows the bench the configuration names: it watches the generator over Modbus (a read-only
    second connection) as a panel wired to its trigger output, and reads the hexapod's and stage's positions over
    GCS when an exposure begins, so each frame shows the object where the axes were. Console commands (one a
    line): latency MS, drop [N], garble [N], error [N], missing [N], match TEXT|-.
    """
    from devices.twins.detector import DetectorTwin
    from devices.twins.world import reset_world

    if config_path is None:
        twin = DetectorTwin(reset_world("standalone panel"))
        what = f"{twin.panel.rows}x{twin.panel.cols} panel, its own unmoving phantom A, software triggers"
    else:
        from acquire.config import BenchConfig, load_config
        from acquire.errors import ConfigError

        try:
            cfg = load_config(config_path)
        except ConfigError as exc:
            fail(str(exc))
        if not isinstance(cfg, BenchConfig):
            fail(f"{config_path}: a C-arm configuration", advice="the C-arm twin has its own panel (orbitct twin carm)")
        uris = cfg.devices.model_dump()
        local = [f"{k} {uris[k]}" for k in _FOLLOWED if uris[k].startswith("sim://")]
        if local:
            fail(
                f"{config_path}: {', '.join(local)} live inside another process",
                advice="a panel of its own follows tcp:// and modbus:// endpoints only (start them with orbitct twin "
                "hexapod|rotation-stage|xray)",
            )
        world = reset_world("standalone panel")
        world.stack_order = cfg.stack.order
        panel = cfg.geometry.detector.panel()
        twin = DetectorTwin(
            world,
            rows=panel.rows,
            cols=panel.cols,
            pitch_mm=(panel.pitch_col, panel.pitch_row),
            sad_mm=cfg.geometry.sad_mm,
            sdd_mm=cfg.geometry.sdd_mm,
            phantom=cfg.sim.imaged(),
            seed=cfg.sim.seed,
            follow={k: uris[k] for k in _FOLLOWED},
        )
        what = (
            f"{panel.rows}x{panel.cols} panel, phantom {cfg.sim.phantom}, following hexapod {uris['hexapod']}, "
            f"rotation_stage {uris['rotation_stage']} and xray {uris['xray']}"
        )
    banner = f"panel twin listening on tcp://{host}:{{}} ({what})"
    serve_twin(twin, host, port, banner.format, console=console)
