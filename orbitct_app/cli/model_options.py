"""Command-line options made from a job's options model, and the model made from what was typed.

A command decorated with :func:`options_from` gets one option per field of the pydantic model (its name, choices,
help with the default and the limits); :func:`model_from` validates what was given by the same model the REST API
and the Python API use, so a value is accepted or refused alike everywhere, and a refusal names the option.
"""

from __future__ import annotations

import types
import typing
from collections.abc import Callable
from typing import Any, TypeVar

import annotated_types
import click
from pydantic import BaseModel, ValidationError
from pydantic.fields import FieldInfo
from pydantic_core import PydanticUndefined

from orbitct_app.cli.values import FiniteFloat

F = TypeVar("F", bound=Callable[..., Any])
M = TypeVar("M", bound=BaseModel)


def flag_of(name: str, flags: dict[str, str]) -> str:
    """The option a field is typed as: ``voxel_mm`` -> ``--voxel-mm`` unless ``flags`` renames it."""
    return flags.get(name, "--" + name.replace("_", "-"))


def _plain(annotation: Any) -> tuple[Any, bool]:
    """The annotation without ``| None``, and whether None was allowed."""
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(annotation) if a is not type(None)]
        return (args[0] if len(args) == 1 else annotation), len(args) < len(typing.get_args(annotation))
    return annotation, False


def field_limits(info: FieldInfo, *, ascii_only: bool = True) -> list[str]:
    """A field's bounds and length limits in words (``>=0.1``, ``length <=3``; ``≥`` and ``≤`` when not
    ``ascii_only``)."""
    ge, le = (">=", "<=") if ascii_only else ("≥", "≤")
    words = []
    for item in info.metadata:
        for attr, word in (("ge", ge), ("gt", ">"), ("le", le), ("lt", "<")):
            if getattr(item, attr, None) is not None:
                words.append(f"{word}{getattr(item, attr)}")
        if isinstance(item, annotated_types.MinLen):
            words.append(f"length {ge}{item.min_length}")
        if isinstance(item, annotated_types.MaxLen):
            words.append(f"length {le}{item.max_length}")
    return words


def _parse_ints(ctx: click.Context, param: click.Parameter, value: str | None) -> list[int] | None:
    if value is None:
        return None
    try:
        return [int(p) for p in value.replace("x", ",").split(",")]
    except ValueError:
        shown = param.metavar or "N,N,..."
        raise click.BadParameter(f"expected {shown}: integers separated by commas, got {value!r}") from None


def _option(name: str, info: FieldInfo, flag: str, metavar: str | None) -> Callable[[F], F]:
    kind, _ = _plain(info.annotation)
    text = (info.description or name.replace("_", " ")).rstrip(".")
    help_text = text[0].upper() + text[1:] + "."
    default = info.default if info.default is not PydanticUndefined else None
    notes = [] if default is None or kind is bool else [f"default: {default}"]
    if kind is bool:
        if default is True:  # on unless turned off: --name / --no-name
            return click.option(f"{flag}/--no-{flag[2:]}", name, default=None, help=help_text + " [default: on]")
        return click.option(flag, name, is_flag=True, default=None, help=help_text)
    if typing.get_origin(kind) is typing.Literal:
        values = typing.get_args(kind)
        if all(isinstance(v, str) for v in values):
            notes_text = f" [{'; '.join(notes)}]" if notes else ""
            return click.option(flag, name, type=click.Choice(values), default=None, help=help_text + notes_text)
        kind = type(values[0])
        notes.append("one of " + ", ".join(map(str, values)))
    elif typing.get_origin(kind) is list:
        inner = typing.get_args(kind)[0]
        limits = field_limits(typing.get_args(inner)[1]) if typing.get_origin(inner) is typing.Annotated else []
        size = next((m.min_length for m in info.metadata if isinstance(m, annotated_types.MinLen)), None)
        metavar = metavar or (",".join(["N"] * size) if size else "N,N,...")
        notes.extend(f"each {w}" for w in limits)
        notes_text = f" [{'; '.join(notes)}]" if notes else ""
        return click.option(
            flag, name, callback=_parse_ints, default=None, metavar=metavar, help=help_text + notes_text
        )
    notes.extend(w for w in field_limits(info) if not w.startswith("length"))
    notes_text = f" [{'; '.join(notes)}]" if notes else ""
    click_type: Any = {int: click.INT, float: FiniteFloat(), str: click.STRING}.get(kind, click.STRING)
    return click.option(flag, name, type=click_type, default=None, help=help_text + notes_text)


def options_from(
    model: type[BaseModel],
    *,
    flags: dict[str, str] | None = None,
    metavars: dict[str, str] | None = None,
    exclude: set[str] | frozenset[str] = frozenset(),
) -> Callable[[F], F]:
    """A decorator adding one click option per field of ``model`` (but ``exclude``), named as :func:`flag_of` says
    (``metavars``: how a list's values are shown in the help)."""
    renamed, shown = flags or {}, metavars or {}

    def decorate(command: F) -> F:
        for name, info in reversed(list(model.model_fields.items())):
            if name not in exclude:
                command = _option(name, info, flag_of(name, renamed), shown.get(name))(command)
        return command

    return decorate


def model_from(model: type[M], values: dict[str, Any], *, flags: dict[str, str] | None = None) -> M:
    """``model`` from the options that were given (None: not given, the model's default applies); a usage error
    (exit status 2) naming the option and what is wrong otherwise."""
    given = {k: v for k, v in values.items() if v is not None}
    try:
        return model.model_validate(given)
    except ValidationError as exc:
        problems = []
        for error in exc.errors():
            field = str(error["loc"][0]) if error["loc"] else ""
            where = f"{flag_of(field, flags or {})}: " if field in model.model_fields else ""
            problems.append(f"{where}{error['msg'].removeprefix('Value error, ')}")
        raise click.UsageError("; ".join(dict.fromkeys(problems))) from None
