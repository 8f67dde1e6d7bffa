"""A job's options refused in words: each option that is wrong and why, in one line."""

from __future__ import annotations

from pydantic import BaseModel, ValidationError


def option_problems(exc: ValidationError, model: type[BaseModel]) -> str:
    """``option: what is wrong`` for each problem ``exc`` found validating ``model``, joined by semicolons; an
    unknown option lists the allowed ones."""
    problems = []
    for error in exc.errors():
        where = ".".join(str(p) for p in error["loc"] if not isinstance(p, int))
        text = error["msg"].removeprefix("Value error, ")
        if error["type"] == "extra_forbidden":
            text = f"unknown option; allowed are {', '.join(model.model_fields)}"
        problems.append(f"{where}: {text}" if where else text)
    return "; ".join(dict.fromkeys(problems))
