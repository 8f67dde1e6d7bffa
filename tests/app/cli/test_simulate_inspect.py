"""CLI: simulate, inspect, orbit list/preview on tiny inputs, and their errors."""

import json
from pathlib import Path

import numpy as np
from click.testing import CliRunner

from orbitct.scanfile import ScanFile
from orbitct_app.cli.main import cli


def test_simulate_then_inspect(tmp_path: Path) -> None:
    out = tmp_path / "scan.h5"
    r = CliRunner().invoke(
        cli,
        [
            "simulate",
            "--experiment",
            "a",
            "--frames",
            "6",
            "--detector-size",
            "48",
            "--darks",
            "2",
            "--flats",
            "3",
            "--seed",
            "4",
            "--out",
            str(out),
        ],
    )
    assert r.exit_code == 0, r.output
    assert "6 projections + 2 darks + 3 flats" in r.output
    with ScanFile(out) as f:
        assert f.count_by_kind() == {"projection": 6, "flat": 3, "dark": 2, "invalid": 0}
        assert f.orbit[0] == "sawtooth" and f.status == "complete"
        assert abs(f.panel.pitch_col - 427.0 / 48) < 1e-12
        assert f.phantom["name"] == "A" and f.truth_markers_xyz().shape == (8, 3)
        nominal, truth = f.geometry("nominal")[5:], f.geometry("truth")[5:]
        assert not nominal.allclose(truth, atol_mm=0.5)  # bench errors were applied
    r = CliRunner().invoke(cli, ["inspect", str(out)])
    assert r.exit_code == 0, r.output
    for text in (
        "complete",
        "6 projection, 3 flat, 2 dark",
        "sawtooth",
        "nominal, truth",
        "3.17 mm",
        "8 markers",
        "rotation 0.0..300.0 deg",
    ):
        assert text in r.output
    assert "warning" not in r.output
    r = CliRunner().invoke(cli, ["inspect", str(out), "--json"])
    assert json.loads(r.output)["frames_by_kind"]["projection"] == 6


def test_inspect_warns_of_projections_taken_away_from_their_command(tmp_path: Path) -> None:
    from tests.helpers.scanfiles import write_sweep_ahead_scan

    write_sweep_ahead_scan(tmp_path / "ahead.h5")
    r = CliRunner().invoke(cli, ["inspect", str(tmp_path / "ahead.h5")])
    assert r.exit_code == 0, r.output
    assert (
        "warning     2 projection(s) read back further from their command than a step of stage.angle (2 deg), "
        "up to 9.5 deg: their nominal geometry is not where they were taken"
    ) in r.output


def test_simulate_orbit_params_and_no_errors(tmp_path: Path) -> None:
    out = tmp_path / "c.h5"
    r = CliRunner().invoke(
        cli,
        [
            "simulate",
            "-e",
            "C",
            "--orbit",
            "circular",
            "-p",
            "tilt_deg=10",
            "--frames",
            "4",
            "--detector-size",
            "32",
            "--errors",
            "none",
            "--darks",
            "0",
            "--flats",
            "1",
            "--out",
            str(out),
        ],
    )
    assert r.exit_code == 0, r.output
    with ScanFile(out) as f:
        assert f.orbit == ("circular", {"n_frames": 4, "range_deg": 360.0, "start_deg": 0.0, "tilt_deg": 10.0})
        assert f.geometry("nominal")[1:].allclose(f.geometry("truth")[1:], atol_mm=1e-9)
        assert np.allclose(f.axes("commanded")["orbit.tilt"][1:], 10.0)


def test_simulate_a_realistic_panel_records_its_model_and_shows_its_dead_columns(tmp_path: Path) -> None:
    args = ["simulate", "-e", "A", "--frames", "4", "--detector-size", "64", "--darks", "1", "--flats", "1"]
    r = CliRunner().invoke(cli, [*args, "--detector", "realistic", "--out", str(tmp_path / "real.h5")])
    assert r.exit_code == 0, r.output
    with ScanFile(tmp_path / "real.h5") as f:
        model = json.loads(f.h5["provenance"].attrs["config_json"])["detector_model"]
        flat = f.frames[1].astype(float)
    assert model["scatter_fraction"] > 0 and model["lag_fraction"] > 0 and model["dead_columns"] == 2
    assert (flat.mean(axis=0) < 1000).sum() == 2  # two columns read only their dark offset
    r = CliRunner().invoke(cli, [*args, "--detector", "grainy", "--out", str(tmp_path / "x.h5")])
    assert r.exit_code == 2 and "'grainy' is not one of 'clean', 'realistic'" in r.output


def test_simulate_a_polychromatic_beam_records_it_and_hardens_the_projections(tmp_path: Path) -> None:
    args = ["simulate", "-e", "C", "--frames", "8", "--detector-size", "48", "--darks", "1", "--flats", "1"]
    for beam in ("mono", "polychromatic"):
        r = CliRunner().invoke(cli, [*args, "--beam", beam, "--out", str(tmp_path / f"{beam}.h5")])
        assert r.exit_code == 0, r.output
    with ScanFile(tmp_path / "polychromatic.h5") as f:
        beam = json.loads(f.h5["provenance"].attrs["config_json"])["beam"]
        poly = f.line_integrals(int(f.projection_indices[0]))
    with ScanFile(tmp_path / "mono.h5") as f:
        assert json.loads(f.h5["provenance"].attrs["config_json"])["beam"] == "mono"
        mono = f.line_integrals(int(f.projection_indices[0]))
    assert beam["kv"] == 90.0 and beam["filter_cu_mm"] == 0.1
    assert not np.allclose(poly, mono, atol=0.05)
    r = CliRunner().invoke(cli, [*args, "--beam", "white", "--out", str(tmp_path / "x.h5")])
    assert r.exit_code == 2 and "'white' is not one of 'mono', 'polychromatic'" in r.output


def test_simulate_anatomy_clutter_on_the_torso(tmp_path: Path) -> None:
    args = ["simulate", "--frames", "8", "--detector-size", "32", "--darks", "0", "--flats", "1"]
    r = CliRunner().invoke(cli, [*args, "-e", "C", "--clutter", "anatomy", "--out", str(tmp_path / "c.h5")])
    assert r.exit_code == 0, r.output
    with ScanFile(tmp_path / "c.h5") as f:
        assert any(p["label"] == "rib 11 left 0" for p in f.phantom["primitives"])
    r = CliRunner().invoke(cli, [*args, "-e", "A", "--clutter", "anatomy", "--out", str(tmp_path / "a.h5")])
    assert r.exit_code == 2 and "anatomy clutter is made for experiment C's torso" in r.output


def test_simulate_takes_the_number_of_frames_as_an_orbit_parameter_too(tmp_path: Path) -> None:
    args = ["simulate", "-e", "A", "--orbit", "circular", "--detector-size", "32", "--darks", "0", "--flats", "1"]
    r = CliRunner().invoke(cli, [*args, "-p", "n_frames=3", "--out", str(tmp_path / "a.h5")])
    assert r.exit_code == 0, r.output
    with ScanFile(tmp_path / "a.h5") as f:
        assert f.orbit[1]["n_frames"] == 3
    r = CliRunner().invoke(cli, [*args, "-p", "n_frames=3", "--frames", "4", "--out", str(tmp_path / "b.h5")])
    assert r.exit_code == 2 and "--frames 4 and -p n_frames=3 disagree" in r.output
    r = CliRunner().invoke(cli, [*args, "-p", "n_frames=3.5", "--out", str(tmp_path / "b.h5")])
    assert r.exit_code == 2 and "is not a whole number of frames" in r.output


def test_simulate_bad_input(tmp_path: Path) -> None:
    run = CliRunner().invoke
    out = tmp_path / "x.h5"
    r = run(cli, ["simulate", "-e", "A", "--orbit", "spiral", "--out", str(out)])
    assert r.exit_code == 2 and "unknown orbit 'spiral'" in r.output
    r = run(cli, ["simulate", "-e", "A", "-p", "amplitude_deg=80", "--out", str(out)])
    assert r.exit_code == 2 and "amplitude_deg" in r.output and "less than or equal to 60" in r.output
    r = run(cli, ["simulate", "-e", "A", "-p", "novalue", "--out", str(out)])
    assert r.exit_code == 2 and "expected KEY=VALUE" in r.output
    r = run(cli, ["simulate", "-e", "Z", "--out", str(out)])
    assert r.exit_code == 2 and "'Z' is not one of" in r.output
    r = run(cli, ["simulate", "-e", "A", "--frames", "1", "--out", str(out)])
    assert r.exit_code == 2
    out.write_text("x")
    r = run(cli, ["simulate", "-e", "A", "--out", str(out)])
    assert r.exit_code == 2 and "already exists" in r.output
    r = run(cli, ["inspect", str(out)])
    assert r.exit_code == 1 and "not a readable HDF5 file" in r.output


def test_orbit_list_and_preview(tmp_path: Path) -> None:
    r = CliRunner().invoke(cli, ["orbit", "list"])
    assert r.exit_code == 0
    for name in ("circular", "sawtooth", "dcarc", "multiarc", "waypoints", "amplitude_deg = 20.0"):
        assert name in r.output
    png = tmp_path / "o.png"
    r = CliRunner().invoke(cli, ["orbit", "preview", "dcarc", "--frames", "60", "--out", str(png)])
    assert r.exit_code == 0, r.output
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    r = CliRunner().invoke(cli, ["orbit", "preview", "multiarc", "-p", "preset=zeego", "--out", str(png)])
    assert r.exit_code == 2 and "preset" in r.output
