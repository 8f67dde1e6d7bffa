"""One options model per job: the command line, the REST API and Python accept and refuse the same options alike,
because all three are made from (or validated by) the same pydantic model."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import click
import pytest
from pydantic import ValidationError

from orbitct_app.cli.model_options import flag_of, model_from
from orbitct_app.cli.reconstruct import FLAGS, reconstruct
from orbitct_app.service.routers.reconstructions import ReconstructionRequest
from recon import ReconError, ReconstructionOptions
from recon.pipeline import checked_options

SCAN_ID = "a1b2c3d4e5f60718"

# (options as Python takes them, whether they are acceptable)
CASES: list[tuple[dict[str, Any], bool]] = [
    ({}, True),
    ({"algorithm": "pwls", "iterations": 1}, True),
    ({"algorithm": "pwls", "iterations": 500, "subsets": 64, "momentum": True}, True),
    ({"iterations": 0}, False),
    ({"iterations": 501}, False),
    ({"subsets": 65}, False),
    ({"voxel_mm": 0.005}, False),
    ({"voxel_mm": 0.006}, True),
    ({"voxel_mm": 20.0}, True),
    ({"voxel_mm": 20.5}, False),
    ({"shape": [4, 4, 4]}, True),
    ({"shape": [3, 64, 64]}, False),
    ({"shape": [2048, 2048, 256]}, True),
    ({"shape": [2048, 2048, 257]}, False),  # more than 1024^3 voxels
    ({"shape": [64, 64]}, False),
    ({"beta": -0.1}, False),
    ({"beta": 0.0}, True),
    ({"neighbourhood": 2}, True),
    ({"neighbourhood": 3}, False),
    ({"geometry": "nominal", "fit": "fov"}, True),
    ({"geometry": "measured"}, False),
    ({"algorithm": "art"}, False),
    ({"window": "ram-lak", "mar": True, "mar_method": "threshold", "mar_threshold": 1.5}, True),
    ({"metal_mu_per_mm": 0.0}, False),
    ({"stream": "disk"}, False),
    ({"name": "fdk_nominal_2"}, True),
    ({"name": "../escape"}, False),
    ({"max_minutes": 0.5}, True),
    ({"max_minutes": 0.0}, False),
    ({"max_minutes": 10081.0}, False),
]


def python_accepts(values: dict[str, Any]) -> bool:
    try:
        checked_options(None, values)
    except ReconError:
        return False
    return True


def rest_accepts(values: dict[str, Any]) -> bool:
    try:
        ReconstructionRequest.model_validate_json(json.dumps({"scan_id": SCAN_ID, **values}))
    except ValidationError:
        return False
    return True


def cli_words(values: dict[str, Any]) -> list[str]:
    """The options a person types for ``values``."""
    words = []
    for name, value in values.items():
        flag = flag_of(name, FLAGS)
        if value is True:
            words.append(flag)
        elif isinstance(value, list):
            words += [flag, ",".join(map(str, value))]
        else:
            words += [flag, str(value)]
    return words


def cli_accepts(values: dict[str, Any], scan: Path) -> bool:
    """Parse as ``orbitct reconstruct SCAN ...`` does, then validate as the command does (nothing is run)."""
    try:
        ctx = reconstruct.make_context("reconstruct", [str(scan), *cli_words(values), "--yes"])
        params = {k: v for k, v in ctx.params.items() if k in ReconstructionOptions.model_fields}
        model_from(ReconstructionOptions, params, flags=FLAGS)
    except click.UsageError:
        return False
    return True


@pytest.mark.parametrize(("values", "acceptable"), CASES, ids=[json.dumps(v) for v, _ in CASES])
def test_the_same_options_get_the_same_answer_everywhere(
    values: dict[str, Any], acceptable: bool, tmp_path: Path
) -> None:
    scan = tmp_path / "scan.h5"
    scan.touch()
    answers = {"python": python_accepts(values), "rest": rest_accepts(values), "cli": cli_accepts(values, scan)}
    assert answers == dict.fromkeys(answers, acceptable), answers


def test_every_option_is_in_every_interface() -> None:
    from orbitct_app.reference_pages import openapi_document

    fields = set(ReconstructionOptions.model_fields)
    cli_names = {p.name for p in reconstruct.params}
    assert fields - cli_names == set()
    body = openapi_document()["components"]["schemas"]["ReconstructionRequest"]["properties"]
    assert fields - set(body) == set()
    assert set(body) - fields == {"scan_id"}


def test_a_refusal_names_the_option_as_it_was_typed(tmp_path: Path) -> None:
    scan = tmp_path / "scan.h5"
    scan.touch()
    ctx = reconstruct.make_context("reconstruct", [str(scan), "--voxel-mm", "50", "--grid", "fov"])
    params = {k: v for k, v in ctx.params.items() if k in ReconstructionOptions.model_fields}
    with pytest.raises(click.UsageError, match=r"--voxel-mm: Input should be less than or equal to 20"):
        model_from(ReconstructionOptions, params, flags=FLAGS)


def test_the_defaults_are_one_set() -> None:
    options = ReconstructionOptions()
    assert options.algorithm == "fdk" and options.iterations == 50 and options.beta == 0.01
    rest = ReconstructionRequest.model_validate_json(json.dumps({"scan_id": SCAN_ID}))
    assert rest.model_dump(exclude={"scan_id"}) == options.model_dump()
