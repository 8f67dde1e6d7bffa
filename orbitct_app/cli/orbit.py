"""``orbitct orbit``: list orbit kinds and draw an orbit's source positions on a sphere."""

from __future__ import annotations

from pathlib import Path

import click

from orbitct_app.cli.simulate import parse_params


@click.group()
def orbit() -> None:
    """Orbit kinds and previews."""


@orbit.command("list")
def list_orbits() -> None:
    """List orbit kinds with their parameters and defaults."""
    from orbitct.orbits import ORBIT_KINDS, describe_kinds

    for name, line in describe_kinds().items():
        click.echo(f"{name:10s} {line}")
        for field, info in ORBIT_KINDS[name].model_fields.items():
            default = info.get_default(call_default_factory=True)
            click.echo(f"    {field} = {default!r}" + (f"  ({info.description})" if info.description else ""))


@orbit.command("preview")
@click.argument("name")
@click.option("--param", "-p", "params", multiple=True, metavar="KEY=VALUE", help="orbit parameter (repeatable)")
@click.option("--frames", type=click.IntRange(min=2), default=None, help="number of frames")
@click.option("--out", "-o", type=click.Path(dir_okay=False, path_type=Path), required=True, help="PNG to write")
def preview(name: str, params: tuple[str, ...], frames: int | None, out: Path) -> None:
    """Draw orbit NAME as source positions on a sphere around the isocenter (PNG)."""
    from orbitct.orbits import OrbitError, make_orbit
    from orbitct.orbits.preview import draw_orbit

    p = parse_params(params)
    if frames is not None:
        p["n_frames"] = frames
    try:
        orb = make_orbit(name, **p)
    except OrbitError as exc:
        raise click.UsageError(str(exc)) from None
    draw_orbit(orb, out)
    click.echo(f"wrote {out}: {orb!r}")
