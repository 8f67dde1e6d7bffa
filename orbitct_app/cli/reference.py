"""``orbitct reference``: servo on and reference a bench's motion axes, an operator's decision that a scan never
takes on its own (referencing moves every axis to its reference switch)."""

from __future__ import annotations

import asyncio
import signal
from pathlib import Path
from typing import Any

import click

from orbitct_app.cli.failure import fail

#: the bench's devices with axes to reference, in the order ``all`` takes them (one at a time: the stage rides on
#: the hexapod or the other way round)
MOTION_DEVICES = ("hexapod", "rotation_stage")


@click.command()
@click.argument("device", type=click.Choice([*MOTION_DEVICES, "all"]))
@click.option(
    "--config",
    "config_path",
    type=click.Path(dir_okay=False, path_type=Path),
    required=True,
    help="The bench configuration naming where the device is reached (config/bench.yaml).",
)
@click.option(
    "--data-dir",
    type=click.Path(file_okay=False, path_type=Path),
    envvar="ORBITCT_DATA_DIR",
    default=None,
    help="The service's data directory (or ORBITCT_DATA_DIR): refuse while its emergency stop is latched.",
)
@click.option("--yes", is_flag=True, help="Do not ask: the axes' travel to their reference switches is clear.")
def reference(device: str, config_path: Path, data_dir: Path | None, yes: bool) -> None:
    """Servo on and reference DEVICE's axes (hexapod, rotation_stage or all), moving each to its reference switch.

    A scan refuses unreferenced axes of real controllers; this is how a bench operator references them without
    the REST service (which has POST /devices/NAME/reference). Already referenced axes are left where they are.
    Ctrl-C, SIGTERM or SIGHUP halt the axes.
    """
    from acquire.config import BenchConfig, load_config
    from acquire.errors import ConfigError

    try:
        config = load_config(config_path)
    except ConfigError as exc:
        fail(str(exc))
    if not isinstance(config, BenchConfig):
        fail(
            f"{config_path}: a C-arm configuration; a C-arm has no axes to reference from here",
            advice="reference the arm from its own console",
        )
    if data_dir is not None:
        from orbitct_app.service.safety.latch import StopLatch

        refused = StopLatch(data_dir).refusal("referencing")
        if refused:
            fail(refused, "stop_latched")
    from acquire.rigs.bench import bench_links

    links = bench_links(config, sim=False)
    names = list(MOTION_DEVICES) if device == "all" else [device]
    for name in names:
        if links[name].uri.startswith("sim://"):
            fail(
                f"{config_path}: {name} is {links[name].uri}, the in-process twins, which are referenced when a "
                "scan opens them",
                advice="reference a real controller (tcp:// or serial://)",
            )
    if not yes:
        where = ", ".join(f"{n} ({links[n].uri})" for n in names)
        if not click.confirm(
            f"Referencing moves every axis of {where} to its reference switch. Is the travel clear?", err=True
        ):
            fail("not confirmed: nothing moved", "action_failed", "clear the travel, then run it again (or --yes)")
    received: list[signal.Signals] = []
    try:
        asyncio.run(_reference_all(names, links, received))
    except (KeyboardInterrupt, asyncio.CancelledError):
        sig = received[0] if received else signal.SIGINT
        fail(
            f"interrupted ({'Ctrl-C' if sig == signal.SIGINT else sig.name}): the axes were halted; they may be "
            "unreferenced",
            "interrupted",
            "reference them again when ready",
            exit_status=128 + int(sig),
        )


async def _reference_all(names: list[str], links: dict[str, Any], received: list[signal.Signals]) -> None:
    from devices.errors import DeviceError
    from devices.factory import open_device

    task, loop = asyncio.current_task(), asyncio.get_running_loop()

    def cancel(sig: signal.Signals) -> None:  # as Ctrl-C: the reference is cancelled and the driver halts the axes
        received.append(sig)
        task.cancel()  # type: ignore[union-attr]

    for sig in (signal.SIGTERM, signal.SIGHUP):
        loop.add_signal_handler(sig, cancel, sig)
    for name in names:
        try:
            dev = await open_device(name, name, links[name].uri, **links[name].options)
        except DeviceError as exc:
            fail(f"{name}: {exc}", "unavailable")
        try:
            before = await dev.referenced()
            if all(before.values()):
                if not all((await dev.servo_on()).values()):
                    await dev.servo(True)
                click.echo(f"{name}: axes {' '.join(before)} already referenced; nothing moved")
                continue
            click.echo(f"{name}: referencing {' '.join(a for a, ok in before.items() if not ok)} ...", err=True)
            await dev.reference()
            where = ", ".join(f"{a} {v:.4g}" for a, v in (await dev.position()).items())
            click.echo(f"{name}: referenced; at {where}")
        except DeviceError as exc:
            fail(f"{name}: {exc}", "action_failed")
        finally:
            await dev.close()
