"""Entry point of the ``orbitct`` command; subcommands are imported only when used."""

from __future__ import annotations

import importlib
import sys

import click

# command name -> "module:attribute" of a click command or group
COMMANDS: dict[str, str] = {
    "simulate": "orbitct_app.cli.simulate:simulate",
    "inspect": "orbitct_app.cli.simulate:inspect",
    "orbit": "orbitct_app.cli.orbit:orbit",
    "plan": "orbitct_app.cli.plan:plan",
    "twin": "orbitct_app.cli.twin:twin",
    "scan": "orbitct_app.cli.scan:scan",
    "demo": "orbitct_app.cli.demo:demo",
    "calibrate": "orbitct_app.cli.calibrate:calibrate",
    "reconstruct": "orbitct_app.cli.reconstruct:reconstruct",
    "export": "orbitct_app.cli.export:export",
    "import": "orbitct_app.cli.imports:import_group",
    "pacs": "orbitct_app.cli.pacs:pacs",
    "serve": "orbitct_app.cli.serve:serve",
    "token": "orbitct_app.cli.serve:token",
    "stop": "orbitct_app.cli.remote:stop",
    "reset": "orbitct_app.cli.remote:reset",
    "reset-fault": "orbitct_app.cli.remote:reset_fault",
    "reference": "orbitct_app.cli.reference:reference",
    "warmup": "orbitct_app.cli.warmup:warmup",
}


class _LazyGroup(click.Group):
    def list_commands(self, ctx: click.Context) -> list[str]:
        return sorted(COMMANDS)

    def get_command(self, ctx: click.Context, cmd_name: str) -> click.Command | None:
        target = COMMANDS.get(cmd_name)
        if target is None:
            return None
        module, attr = target.split(":")
        return getattr(importlib.import_module(module), attr)

    def invoke(self, ctx: click.Context) -> object:
        """Every command; a file that cannot be read or written (a missing folder, no permission, a full disk)
        ends it with one line naming the file, never a traceback."""
        try:
            return super().invoke(ctx)
        except OSError as exc:
            where = f"{exc.filename}: " if exc.filename else ""
            raise click.ClickException(f"{where}{exc.strerror or exc}") from None


@click.group(cls=_LazyGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="orbitct")
def cli() -> None:
    """orbitct: drive non-circular CT orbits, acquire, calibrate from BBs, reconstruct."""


def main() -> None:
    """Console entry point."""
    cli(prog_name="orbitct")


if __name__ == "__main__":
    sys.exit(main())
