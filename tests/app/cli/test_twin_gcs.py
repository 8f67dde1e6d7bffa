"""``orbitct twin hexapod`` / ``rotation-stage`` run standalone and the driver connects to them."""

from __future__ import annotations

import os
import signal
import subprocess
import sys

import pytest

from devices.hexapod import Hexapod
from devices.rotation_stage import RotationStage

pytestmark = [pytest.mark.anyio, pytest.mark.system]


def _start(*args: str) -> tuple[subprocess.Popen[str], str]:
    cmd = [sys.executable, "-m", "orbitct_app.cli.main", "twin", *args, "--host", "127.0.0.1", "--port", "0"]
    proc = subprocess.Popen(
        cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"}
    )
    assert proc.stdout is not None
    line = proc.stdout.readline()
    assert "listening on tcp://" in line, line
    return proc, line.split("listening on ")[1].split()[0]


def _stop(proc: subprocess.Popen[str]) -> None:
    proc.send_signal(signal.SIGINT)
    try:
        proc.wait(10)
    except subprocess.TimeoutExpired:
        proc.kill()


async def test_cli_hexapod_twin_with_faults() -> None:
    proc, uri = _start("hexapod", "--time-scale", "50", "--error", "17:VLS", "--latency-ms", "1")
    try:
        dev = Hexapod("hexapod", uri)
        await dev.connect()
        try:
            await dev.reference()
            await dev.move({"Y": 2.0})
            assert (await dev.position())["Y"] == pytest.approx(2.0, abs=1e-3)
            with pytest.raises(Exception, match="17"):
                await dev.set_velocity(5.0)
        finally:
            await dev.close()
    finally:
        _stop(proc)
    assert proc.returncode == 0


async def test_cli_rotation_stage_twin() -> None:
    proc, uri = _start("rotation-stage", "--perfect", "--stuck-axis", "1")
    try:
        dev = RotationStage("stage", uri, move_timeout_s=0.3)
        await dev.connect()
        try:
            assert (await dev.describe()).axes[0].name == "R"
        finally:
            await dev.close()
    finally:
        _stop(proc)


def test_cli_rejects_bad_fault_spec() -> None:
    cmd = [sys.executable, "-m", "orbitct_app.cli.main", "twin", "hexapod", "--port", "0", "--error", "MOV"]
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
    assert out.returncode != 0 and "CODE:COMMAND" in out.stderr
