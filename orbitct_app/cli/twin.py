"""``orbitct twin ...``: start one simulated device standalone on a real socket."""

from __future__ import annotations

import importlib

import click

TWINS: dict[str, str] = {
    "hexapod": "orbitct_app.cli.twin_gcs:hexapod",
    "rotation-stage": "orbitct_app.cli.twin_gcs:rotation_stage",
    "xray": "orbitct_app.cli.twin_xray:xray",
    "carm": "orbitct_app.cli.twin_carm:carm",
}


class _TwinGroup(click.Group):
    def list_commands(self, ctx: click.Context) -> list[str]:
        return sorted(TWINS)

    def get_command(self, ctx: click.Context, cmd_name: str) -> click.Command | None:
        target = TWINS.get(cmd_name)
        if target is None:
            return None
        module, attr = target.split(":")
        return getattr(importlib.import_module(module), attr)


@click.group(cls=_TwinGroup)
def twin() -> None:
    """Run a device twin until Ctrl-C (hexapod, rotation-stage, xray, carm)."""
