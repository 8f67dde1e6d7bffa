"""The documentation's reference pages, generated from the code so they cannot drift from it.

Each function returns one Markdown page: every command and option of the ``orbitct`` command line (from its click
parser), every route of the REST API (from the service's OpenAPI document), every configuration key (from the
pydantic models of the bench, C-arm and service settings) and every error code and operator advice. The
documentation's build hook (``docs/hooks/reference.py``) writes them into the site; ``tests/app/test_docs.py`` checks
that nothing is missing from them.
"""

from __future__ import annotations

import json
import tempfile
import types
import typing
from collections.abc import Iterator
from typing import Any

import click
from pydantic import BaseModel
from pydantic.fields import FieldInfo
from pydantic_core import PydanticUndefined

from orbitct_app.cli.model_options import field_limits

PAGES = {
    "reference/cli.md": "cli_page",
    "reference/rest-api.md": "rest_page",
    "reference/configuration.md": "configuration_page",
    "reference/errors.md": "errors_page",
}


def _cell(text: object) -> str:
    """Text for one cell of a Markdown table."""
    return str(text).replace("|", "\\|").replace("\n", " ").strip()


# --- the command line ----------------------------------------------------------------------------------------------


def walk_commands(
    command: click.Command, path: tuple[str, ...] = ("orbitct",)
) -> Iterator[tuple[tuple[str, ...], click.Command]]:
    """Every command and subcommand, depth first, with its full name."""
    yield path, command
    if isinstance(command, click.Group):
        ctx = click.Context(command, info_name=path[-1])
        for name in command.list_commands(ctx):
            sub = command.get_command(ctx, name)
            if sub is not None and not sub.hidden:
                yield from walk_commands(sub, (*path, name))


def _help_text(path: tuple[str, ...], command: click.Command) -> str:
    parent = None
    for name in path[:-1]:
        parent = click.Context(click.Command(name), info_name=name, parent=parent)
    ctx = click.Context(command, info_name=path[-1], parent=parent, terminal_width=110, max_content_width=110)
    return command.get_help(ctx)


def cli_page() -> str:
    """Every command of ``orbitct`` with the help it prints."""
    from orbitct_app.cli.main import cli

    lines = [
        "# Command line",
        "",
        "Generated from the command line's own parser: each section is what `--help` prints.",
        "",
    ]
    for path, command in walk_commands(cli):
        title = " ".join(path)
        lines += [f"## `{title}`", "", "```text", _help_text(path, command).rstrip(), "```", ""]
    return "\n".join(lines)


# --- the REST API --------------------------------------------------------------------------------------------------


def openapi_document() -> dict[str, Any]:
    """The service's OpenAPI document, made without starting the service (a throwaway data folder)."""
    from orbitct_app.service.app import create_app
    from orbitct_app.service.core.settings import load_settings

    with tempfile.TemporaryDirectory(prefix="orbitct-openapi-") as folder:
        app = create_app(load_settings(data_dir=folder))
        document = app.openapi()
        app.state.service.close()
    return document


def _schema_type(schema: dict[str, Any]) -> str:
    if "$ref" in schema:
        name = schema["$ref"].rsplit("/", 1)[-1]
        return f"[{name}](#{name.lower()})"
    if "anyOf" in schema:
        return " or ".join(_schema_type(s) for s in schema["anyOf"])
    if "allOf" in schema and len(schema["allOf"]) == 1:
        return _schema_type(schema["allOf"][0])
    if "enum" in schema:
        return " or ".join(f"`{json.dumps(v)}`" for v in schema["enum"])
    if "const" in schema:
        return f"`{json.dumps(schema['const'])}`"
    kind = schema.get("type", "any")
    if kind == "array":
        return f"list of {_schema_type(schema.get('items', {}))}"
    if kind == "object" and "additionalProperties" in schema and isinstance(schema["additionalProperties"], dict):
        return f"map to {_schema_type(schema['additionalProperties'])}"
    return str(kind)


_LIMIT_WORDS = {
    "minimum": "≥",
    "exclusiveMinimum": ">",
    "maximum": "≤",
    "exclusiveMaximum": "<",
    "minLength": "length ≥",
    "maxLength": "length ≤",
    "minItems": "items ≥",
    "maxItems": "items ≤",
    "pattern": "matches",
}


def _schema_limits(schema: dict[str, Any]) -> str:
    found = []
    for part in [schema, *schema.get("anyOf", [])]:
        for key, word in _LIMIT_WORDS.items():
            if key in part:
                found.append(f"{word} `{part[key]}`" if key == "pattern" else f"{word} {part[key]}")
    return ", ".join(found)


def rest_page() -> str:
    """Every route of the REST API with its roles, parameters, body and answers, and every schema it uses."""
    document = openapi_document()
    lines = [
        "# REST API",
        "",
        f"Generated from the OpenAPI document of orbitct {document['info']['version']} (`GET /openapi.json` on a "
        "running service, which also serves Swagger UI at `/docs` and ReDoc at `/redoc`).",
        "",
        document["info"].get("description", ""),
        "",
    ]
    for route, operations in document["paths"].items():
        for method, operation in operations.items():
            lines += [f"## `{method.upper()} {route}`", ""]
            if operation.get("summary"):
                lines += [f"**{_cell(operation['summary'])}**", ""]
            if operation.get("description"):
                lines += [operation["description"].strip(), ""]
            parameters = operation.get("parameters", [])
            if parameters:
                lines += [
                    "| parameter | in | type | required | limits | description |",
                    "| --- | --- | --- | --- | --- | --- |",
                ]
                for p in parameters:
                    schema = p.get("schema", {})
                    lines.append(
                        f"| `{p['name']}` | {p['in']} | {_cell(_schema_type(schema))} | "
                        f"{'yes' if p.get('required') else 'no'} | {_cell(_schema_limits(schema))} | "
                        f"{_cell(p.get('description', schema.get('description', '')))} |"
                    )
                lines.append("")
            body = operation.get("requestBody", {}).get("content", {})
            for media, content in body.items():
                lines += [f"Body ({media}): {_schema_type(content.get('schema', {}))}", ""]
            lines += ["| answer | meaning |", "| --- | --- |"]
            for status, answer in operation.get("responses", {}).items():
                lines.append(f"| {status} | {_cell(answer.get('description', ''))} |")
            lines.append("")
    lines += ["## Schemas", ""]
    for name, schema in sorted(document.get("components", {}).get("schemas", {}).items()):
        lines += [f"### {name}", ""]
        if schema.get("description"):
            lines += [schema["description"].strip(), ""]
        properties = schema.get("properties", {})
        if properties:
            required = set(schema.get("required", []))
            lines += [
                "| field | type | required | default | limits | description |",
                "| --- | --- | --- | --- | --- | --- |",
            ]
            for field, spec in properties.items():
                default = f"`{json.dumps(spec['default'])}`" if "default" in spec else ""
                lines.append(
                    f"| `{field}` | {_cell(_schema_type(spec))} | {'yes' if field in required else 'no'} | "
                    f"{_cell(default)} | {_cell(_schema_limits(spec))} | {_cell(spec.get('description', ''))} |"
                )
            lines.append("")
        elif "enum" in schema:
            lines += [f"One of {_schema_type(schema)}.", ""]
    return "\n".join(lines)


# --- configuration -------------------------------------------------------------------------------------------------


def _type_name(annotation: Any) -> str:
    origin = typing.get_origin(annotation)
    if origin is typing.Annotated:
        return _type_name(typing.get_args(annotation)[0])
    if origin in (typing.Union, types.UnionType):
        return " or ".join(_type_name(a) for a in typing.get_args(annotation))
    if origin is typing.Literal:
        return " or ".join(f"`{json.dumps(a)}`" for a in typing.get_args(annotation))
    if origin in (list, tuple, dict):
        inner = ", ".join(_type_name(a) for a in typing.get_args(annotation) if a is not Ellipsis)
        return f"{origin.__name__}[{inner}]"
    if annotation is type(None):
        return "none"
    return getattr(annotation, "__name__", str(annotation))


def _default(info: FieldInfo) -> str:
    if info.default_factory is not None:
        value = info.default_factory()  # type: ignore[call-arg]
    elif info.default is PydanticUndefined:
        return "required"
    else:
        value = info.default
    if isinstance(value, BaseModel):
        return "(section)"
    if isinstance(value, tuple):
        value = list(value)
    try:
        return f"`{json.dumps(value)}`"
    except TypeError:
        return f"`{value}`"


def _section_model(annotation: Any) -> type[BaseModel] | None:
    candidates = [annotation, *typing.get_args(annotation)]
    for candidate in candidates:
        if isinstance(candidate, type) and issubclass(candidate, BaseModel):
            return candidate
    return None


def config_keys(model: type[BaseModel], prefix: str = "") -> Iterator[tuple[str, FieldInfo, type[BaseModel] | None]]:
    """Every key of a configuration model, sections first, as dotted paths."""
    for name, info in model.model_fields.items():
        key = f"{prefix}{name}"
        section = _section_model(info.annotation)
        yield key, info, section
        if section is not None:
            yield from config_keys(section, f"{key}.")


def _first_line(text: str | None) -> str:
    return (text or "").strip().splitlines()[0] if (text or "").strip() else ""


def _config_table(title: str, intro: str, model: type[BaseModel]) -> list[str]:
    lines = [
        f"## {title}",
        "",
        intro,
        "",
        "| key | type | default | limits | description |",
        "| --- | --- | --- | --- | --- |",
    ]
    for key, info, section in config_keys(model):
        kind = f"section ({section.__name__})" if section is not None else _cell(_type_name(info.annotation))
        description = info.description or (_first_line(section.__doc__) if section is not None else "")
        lines.append(
            f"| `{key}` | {kind} | {_cell(_default(info))} | {', '.join(field_limits(info, ascii_only=False))} | {_cell(description)} |"
        )
    return [*lines, ""]


def configuration_page() -> str:
    """Every key of the bench and C-arm configurations and of the service's settings."""
    from acquire.config import BenchConfig, CArmConfig
    from orbitct_app.service.core.settings import ServiceSettings

    lines = [
        "# Configuration",
        "",
        "Generated from the pydantic models that read the files, so every key, type, default and limit here is the "
        "one orbitct applies. Units are in the names (`_mm`, `_deg`, `_ms`, `_s`, `_hz`); a range is "
        "`[low, high]`. Unknown keys are refused with the key named.",
        "",
    ]
    lines += _config_table(
        "Bench (`config/bench.yaml`)",
        "The hexapod and rotation stage test bench: `orbitct scan --config config/bench.yaml`.",
        BenchConfig,
    )
    lines += _config_table(
        "C-arm (`config/carm-zeego.yaml`)",
        "A robotic C-arm driven by navigation points: `orbitct scan --config config/carm-zeego.yaml`.",
        CArmConfig,
    )
    lines += _config_table(
        "Service settings (`orbitct serve`)",
        "Each key comes from the settings file (`orbitct serve --settings FILE`), from the environment as "
        "`ORBITCT_<KEY>` or from the command line's options.",
        ServiceSettings,
    )
    return "\n".join(lines)


# --- errors --------------------------------------------------------------------------------------------------------


def errors_page() -> str:
    """The error catalogue (every code of the CLI and the API) and what an operator does after each kind of device
    failure."""
    from acquire.reasons import ADVICE
    from devices.errors import DeviceError
    from orbitct_app.error_codes import CATALOGUE

    lines = [
        "# Errors",
        "",
        "Every error reaches a person as one sentence: what happened, then what to do next. Scripts read the stable "
        "code, which does not change between versions. Generated from the catalogue the CLI and the service use "
        "(`orbitct_app/error_codes.py`).",
        "",
        "* **Command line**: one line on stderr, `error [CODE]: what happened; what to do`, and the exit status "
        "below (a command stopped by a signal exits 128 + the signal's number, 130 for Ctrl-C). Warnings are "
        "lines `warning: ...`; `ORBITCT_DEBUG=1` shows the traceback of an unexpected error.",
        '* **REST API**: the HTTP status below and the JSON body `{"error": CODE, "message": "what happened; what '
        'to do", "advice": "what to do", "details": [{"field", "reason"}]}` (`details` for invalid fields).',
        "* **Jobs** (calibrations, reconstructions, BB plans) that fail say why in their `reason`, in the same "
        "words, and a job's log ends with `error [CODE]: ...`; a calibration that failed its quality check has the "
        "verdict and its reasons.",
        "",
        "## The catalogue",
        "",
        "| code | exit status | HTTP status | when | what to do (unless the message says more precisely) |",
        "| --- | --- | --- | --- | --- |",
    ]
    for kind in CATALOGUE.values():
        exit_status = str(kind.exit_status) if kind.exit_status is not None else "-"
        http_status = str(kind.http_status) if kind.http_status is not None else "-"
        lines.append(
            f"| `{kind.code}` | {exit_status} | {http_status} | {_cell(kind.meaning)} | {_cell(kind.advice)} |"
        )
    lines += [
        "",
        "## Why a scan ended",
        "",
        "A scan that a device ends says what the device reported, then what to do; the first row that matches "
        "applies. A failure that is orbitct's own says so and asks for a report; the log has the details.",
        "",
        "| device failure | what to do |",
        "| --- | --- |",
    ]
    for failure, advice in ADVICE:
        what = "Any other device failure." if failure is DeviceError else _first_line(failure.__doc__)
        lines.append(f"| {_cell(what)} | {_cell(advice)} |")
    return "\n".join([*lines, ""])
