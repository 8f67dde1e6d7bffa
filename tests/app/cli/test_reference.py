"""``orbitct reference``: a bench operator references real controllers' axes (twins on TCP) before a scan."""

from __future__ import annotations

import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest
import yaml
from click.testing import CliRunner

from devices.twins.gcs import start_twin
from devices.twins.runtime import TwinThread
from orbitct_app.cli.main import cli

pytestmark = [pytest.mark.timeout(120), pytest.mark.system]
ROOT = Path(__file__).resolve().parents[3]


@pytest.fixture
def twins() -> Iterator[tuple[TwinThread, TwinThread]]:
    world = f"ref-{uuid.uuid4().hex[:8]}"
    hexapod = start_twin("hexapod", world=world, time_scale=100.0)
    stage = start_twin("rotation_stage", world=world, time_scale=100.0)
    yield hexapod, stage
    hexapod.stop()
    stage.stop()


def _config(tmp_path: Path, hexapod: str, stage: str) -> Path:
    data = yaml.safe_load((ROOT / "config" / "bench.yaml").read_text())
    data["devices"].update({"hexapod": hexapod, "rotation_stage": stage})
    path = tmp_path / "bench.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def _referenced(twin: TwinThread) -> bool:
    return bool(twin.twin.controller.referenced.all())


def test_references_every_axis_once_the_operator_confirms(tmp_path: Path, twins: tuple[TwinThread, TwinThread]) -> None:
    hexapod, stage = twins
    config = str(_config(tmp_path, hexapod.uri, stage.uri))
    r = CliRunner().invoke(cli, ["reference", "all", "--config", config], input="n\n")
    assert r.exit_code == 1 and "reference switch" in r.output and not _referenced(hexapod) and not _referenced(stage)
    r = CliRunner().invoke(cli, ["reference", "all", "--config", config], input="y\n")
    assert r.exit_code == 0, r.output
    assert "hexapod: referenced" in r.output and "rotation_stage: referenced" in r.output
    assert _referenced(hexapod) and _referenced(stage)
    r = CliRunner().invoke(cli, ["reference", "hexapod", "--config", config, "--yes"])
    assert r.exit_code == 0 and "already referenced; nothing moved" in r.output, r.output


def test_refused_while_the_stop_is_latched_and_for_twins_or_a_carm(
    tmp_path: Path, twins: tuple[TwinThread, TwinThread]
) -> None:
    from orbitct_app.service.safety.latch import StopLatch

    hexapod, stage = twins
    config = str(_config(tmp_path, hexapod.uri, stage.uri))
    StopLatch(tmp_path / "data").engage("tester", "the door was open", "test")
    r = CliRunner().invoke(
        cli, ["reference", "hexapod", "--config", config, "--yes", "--data-dir", str(tmp_path / "data")]
    )
    assert r.exit_code == 2 and "tester" in r.output and not _referenced(hexapod), r.output
    r = CliRunner().invoke(cli, ["reference", "hexapod", "--config", str(ROOT / "config" / "bench.yaml"), "--yes"])
    assert r.exit_code == 2 and "sim://bench" in r.output and "in-process twins" in r.output, r.output
    r = CliRunner().invoke(cli, ["reference", "all", "--config", str(ROOT / "config" / "carm-zeego.yaml"), "--yes"])
    assert r.exit_code == 2 and "C-arm" in r.output, r.output
    r = CliRunner().invoke(
        cli, ["reference", "all", "--config", str(_config(tmp_path, "tcp://127.0.0.1:9", stage.uri)), "--yes"]
    )
    assert r.exit_code == 1 and r.output.startswith("error [unavailable]: hexapod:") and "Traceback" not in r.output, (
        r.output
    )


def test_sigterm_while_referencing_halts_the_axes(tmp_path: Path) -> None:
    import signal
    import subprocess
    import sys

    hexapod = start_twin("hexapod", world=f"ref-{uuid.uuid4().hex[:8]}", time_scale=0.05)  # referencing takes minutes
    try:
        config = str(_config(tmp_path, hexapod.uri, "tcp://127.0.0.1:9"))
        cmd = [
            sys.executable,
            "-c",
            "from orbitct_app.cli.main import main; main()",
            "reference",
            "hexapod",
            "--config",
            config,
            "--yes",
        ]
        proc = subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True)
        assert proc.stderr is not None
        assert "referencing X Y Z U V W" in proc.stderr.readline()
        proc.send_signal(signal.SIGTERM)
        rest = proc.stderr.read()
        assert proc.wait(30) == 128 + signal.SIGTERM and "interrupted (SIGTERM): the axes were halted" in rest, rest
        controller = hexapod.twin.controller
        assert not controller.referencing and not controller.motion.moving().any() and not controller.referenced.any()
    finally:
        hexapod.stop()
