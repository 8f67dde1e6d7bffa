"""Cross-field rules of request bodies in JSON Schema, so that the OpenAPI document says what a request may hold.

Pydantic validators enforce these rules; the fragments here state the same rules in the schema (OpenAPI 3.1, JSON
Schema 2020-12), for clients and contract tests. Rules JSON Schema cannot state (one field below another) are in the
fields' descriptions instead.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any


def at_most_one_of(*fields: str) -> dict[str, Any]:
    """At most one of ``fields`` is given (absent or null counts as not given)."""
    return {
        "anyOf": [{"properties": {other: {"type": "null"} for other in fields if other != keep}} for keep in fields]
    }


def only_with(field: str, other: str, value: Any) -> dict[str, Any]:
    """A non-empty ``field`` (a list) only when ``other`` is ``value``."""
    return {
        "anyOf": [
            {"properties": {field: {"anyOf": [{"type": "null"}, {"type": "array", "maxItems": 0}]}}},
            {"required": [other], "properties": {other: {"const": value}}},
        ]
    }


def schema_extra(examples: list[dict[str, Any]], *rules: dict[str, Any]) -> Callable[[dict[str, Any]], None]:
    """A model's ``json_schema_extra``: its examples, and its cross-field rules (all of them must hold)."""

    def extra(schema: dict[str, Any]) -> None:
        schema["examples"] = examples
        if rules:
            schema["allOf"] = [*schema.get("allOf", []), *rules]

    return extra
