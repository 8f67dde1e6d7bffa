"""``orbitct twin ...``: start one simulated device standalone on a real socket."""

from __future__ import annotations

import click

from orbitct_app.cli.twin_carm import carm
from orbitct_app.cli.twin_detector import detector
from orbitct_app.cli.twin_gcs import hexapod, rotation_stage
from orbitct_app.cli.twin_xray import xray


@click.group()
def twin() -> None:
    """Run a device twin until Ctrl-C (hexapod, rotation-stage, xray, detector, carm)."""


for command in (hexapod, rotation_stage, xray, detector, carm):
    twin.add_command(command)
