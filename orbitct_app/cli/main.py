"""Entry point of the ``orbitct`` command; subcommands are imported only when used."""

from __future__ import annotations

import importlib
import os

import click

from orbitct_app.cli.failure import as_failure

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

    def parse_args(self, ctx: click.Context, args: list[str]) -> list[str]:
        """``orbitct``'s own options; a wrong one reads as the commands' errors do."""
        try:
            return super().parse_args(ctx, args)
        except click.exceptions.NoArgsIsHelpError:
            raise
        except click.UsageError as exc:
            raise as_failure(exc, ctx) from None

    def invoke(self, ctx: click.Context) -> object:
        """Every command; whatever ends it in error (a usage error, a file that cannot be read or written, a full
        disk, anything unexpected) ends it with one ``error [code]: ...`` line, never a traceback."""
        try:
            return super().invoke(ctx)
        except (click.exceptions.Exit, SystemExit):
            raise
        except (Exception, KeyboardInterrupt) as exc:
            if os.environ.get("ORBITCT_DEBUG") and not isinstance(exc, click.ClickException):
                raise
            raise as_failure(exc, ctx) from None


@click.group(cls=_LazyGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="orbitct")
def cli() -> None:
    """orbitct: drive non-circular CT orbits, acquire, calibrate from BBs, reconstruct."""


def main() -> None:
    """Console entry point."""
    cli(prog_name="orbitct")


if __name__ == "__main__":
    main()
