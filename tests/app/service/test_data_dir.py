"""One service per data directory: a second one is refused with a message naming the first, which keeps its scan."""

from __future__ import annotations

import socket
from pathlib import Path

import pytest
from click.testing import CliRunner

from orbitct_app.cli.main import cli
from orbitct_app.service.core.datadir import DataDirBusy
from tests.helpers.service import SMALL_SAWTOOTH, ended, free_port, small_bench_config, wait_for

pytestmark = [pytest.mark.system, pytest.mark.timeout(180)]


def test_a_second_service_on_the_same_data_directory_is_refused(make_api, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    api = make_api()
    r = api.post("/scans", json={**SMALL_SAWTOOTH, "frames": 60})
    assert r.status_code == 202, r.text
    scan_id = r.json()["id"]
    with pytest.raises(DataDirBusy, match=r"another orbitct service \(pid \d+.*uses the data directory"):
        make_api()  # same data directory
    result = CliRunner().invoke(
        cli,
        [
            "serve",
            "--config",
            str(small_bench_config(tmp_path)),
            "--sim",
            "--data-dir",
            str(api.data_dir),
            "--port",
            str(free_port()),
            "--stop-port",
            "0",
        ],
    )
    assert result.exit_code == 1 and "another orbitct service" in result.output and "--data-dir" in result.output
    assert "Traceback" not in result.output
    scan = wait_for(api, f"/scans/{scan_id}", ended)
    assert scan["state"] == "complete", scan  # the first service's scan was not marked interrupted


def test_serve_refuses_a_port_in_use_before_announcing_itself(tmp_path: Path) -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        result = CliRunner().invoke(
            cli,
            [
                "serve",
                "--config",
                str(small_bench_config(tmp_path)),
                "--sim",
                "--data-dir",
                str(tmp_path / "data"),
                "--port",
                str(port),
            ],
        )
    assert result.exit_code == 1, result.output
    assert f"cannot listen on 127.0.0.1:{port}" in result.output and "choose another --port" in result.output
    assert "orbitct service on" not in result.output and "token" not in result.output


def test_serve_sim_without_a_configuration_runs_the_built_in_bench(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from acquire.config import BenchConfig, load_config

    monkeypatch.chdir(tmp_path)  # no config/bench.yaml here, as after `pip install orbitct`
    with socket.socket() as taken:  # the command stops at the port check, after choosing its configuration
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        sim = CliRunner().invoke(cli, ["serve", "--sim", "--data-dir", "data", "--port", str(port)])
        real = CliRunner().invoke(cli, ["serve", "--data-dir", "data", "--port", str(port)])
    assert "the built-in simulated bench (data/bench-defaults.yaml)" in sim.output, sim.output
    assert load_config(tmp_path / "data" / "bench-defaults.yaml") == BenchConfig()
    assert real.exit_code == 2 and "bench configuration config/bench.yaml does not exist" in real.output
