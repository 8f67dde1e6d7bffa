"""``orbitct scan`` end to end on the in-process twins, and its refusals."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml
from click.testing import CliRunner

from orbitct.scanfile import ScanFile
from orbitct_app.cli.main import cli
from tests.helpers.bench import small_config

pytestmark = [pytest.mark.timeout(120), pytest.mark.system]


def _config_file(tmp_path: Path, *, tilt_limit_deg: float | None = None) -> Path:
    p = tmp_path / "bench.yaml"
    data = small_config().model_dump(mode="json")
    if tilt_limit_deg is not None:  # a bench whose hexapod tilts less than the orbit needs
        data["limits"]["hexapod"]["u_deg"] = [-tilt_limit_deg, tilt_limit_deg]
    p.write_text(yaml.safe_dump(data))
    return p


def test_scan_command_writes_a_file(tmp_path: Path) -> None:
    out = tmp_path / "scan.h5"
    args = [
        "scan",
        "--config",
        str(_config_file(tmp_path)),
        "--orbit",
        "circular",
        "--frames",
        "12",
        "--errors",
        "none",
        "--sim",
        "--out",
        str(out),
    ]
    result = CliRunner().invoke(cli, args)
    assert result.exit_code == 0, result.output
    assert "complete: 18/18 frames (12 projections, 6 darks and flats) in " in result.output
    with ScanFile(out) as sf:
        assert sf.status == "complete" and sf.orbit[0] == "circular"
    again = CliRunner().invoke(cli, args)  # refuses to overwrite
    assert again.exit_code == 2 and "already exists" in again.output


def test_infeasible_orbit_is_refused_before_anything_moves(tmp_path: Path) -> None:
    out = tmp_path / "never.h5"
    config = _config_file(tmp_path, tilt_limit_deg=15.0)
    result = CliRunner().invoke(
        cli,
        [
            "scan",
            "--config",
            str(config),
            "--orbit",
            "sawtooth",
            "--frames",
            "40",
            "--errors",
            "none",
            "--sim",
            "--out",
            str(out),
        ],
    )
    # this bench's hexapod tilts +-15 deg at most; the paper's sawtooth needs +-20 deg
    assert result.exit_code == 2
    assert "orbit infeasible at frame" in result.output and "hexapod.U" in result.output
    assert "nothing moved" in result.output and not out.exists()


@pytest.mark.parametrize(
    "args,message",
    [
        (["--orbit", "zigzag"], "unknown orbit"),
        (["--errors", "gremlins"], "'--errors': 'gremlins' is not one of 'none', 'bench', 'custom'"),
    ],
)
def test_bad_names_are_refused(tmp_path: Path, args: list[str], message: str) -> None:
    result = CliRunner().invoke(
        cli, ["scan", "--config", str(_config_file(tmp_path)), "--sim", "--out", str(tmp_path / "x.h5"), *args]
    )
    assert result.exit_code == 2 and message in result.output


def test_invalid_config_file_is_refused(tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("geometry:\n  sad_mm: 1300\n")
    result = CliRunner().invoke(cli, ["scan", "--config", str(bad), "--sim", "--out", str(tmp_path / "x.h5")])
    assert result.exit_code == 2 and "geometry: sdd_mm (1200.0) must exceed sad_mm (1300.0)" in result.output


def test_orbit_parameters_from_the_command_line(tmp_path: Path) -> None:
    out = tmp_path / "p.h5"
    result = CliRunner().invoke(
        cli,
        [
            "scan",
            "--config",
            str(_config_file(tmp_path)),
            "--orbit",
            "sawtooth",
            "--frames",
            "12",
            "-p",
            "amplitude_deg=5",
            "-p",
            "cycles=1",
            "--errors",
            "none",
            "--sim",
            "--out",
            str(out),
        ],
    )
    assert result.exit_code == 0, result.output
    with ScanFile(out) as sf:
        assert sf.orbit[1]["amplitude_deg"] == 5 and sf.orbit[1]["cycles"] == 1
    bad = CliRunner().invoke(
        cli,
        [
            "scan",
            "--config",
            str(_config_file(tmp_path)),
            "-p",
            "amplitude_deg",
            "--sim",
            "--out",
            str(tmp_path / "q.h5"),
        ],
    )
    assert bad.exit_code == 2 and "is not KEY=VALUE; write it as KEY=VALUE" in bad.output


def test_the_twins_image_the_bbs_of_a_plan(tmp_path: Path) -> None:
    """``--bbs-from``: the twins' object carries a plan's BBs (as ``simulate --bbs-from``); the file's truth says so."""
    import json

    import numpy as np

    plan = tmp_path / "plan.json"
    xyz = [[40.0, 0.0, -20.0], [0.0, 40.0, 0.0], [-40.0, 0.0, 20.0], [0.0, -40.0, 10.0], [28.0, 28.0, -10.0]]
    plan.write_text(json.dumps({"experiment": "A", "bb_diameter_mm": 2.5, "bbs": [{"xyz_mm": c} for c in xyz]}))
    config, out = _config_file(tmp_path), tmp_path / "planned.h5"
    args = ["scan", "--config", str(config), "--orbit", "circular", "--frames", "8", "--out", str(out)]
    result = CliRunner().invoke(cli, [*args, "--sim", "--bbs-from", str(plan)])
    assert result.exit_code == 0, result.output
    with ScanFile(out) as sf:
        np.testing.assert_allclose(sf.truth_markers_xyz(), xyz)
        assert sf.marker_diameter_mm == 2.5 and len(sf.phantom["primitives"]) > len(xyz)
    refused = CliRunner().invoke(cli, [*args, "--overwrite", "--bbs-from", str(plan)])
    assert refused.exit_code == 2 and "--bbs-from needs --sim" in refused.output
    plan.write_text(json.dumps({"experiment": "C", "bb_diameter_mm": 2.0, "bbs": [{"xyz_mm": c} for c in xyz]}))
    refused = CliRunner().invoke(cli, [*args, "--overwrite", "--sim", "--bbs-from", str(plan)])
    assert refused.exit_code == 2 and "was planned for experiment C" in refused.output
    assert "plan for experiment A (orbitct plan bbs -e A)" in refused.output
