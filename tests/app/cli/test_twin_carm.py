"""``orbitct twin carm`` and ``orbitct twin xray`` as separate processes, driven over TCP."""

from __future__ import annotations

import asyncio
import subprocess
import sys

import numpy as np
import pytest

from devices.carm import CArm
from devices.carm_program import export_program
from devices.errors import ControllerError, InterlockOpenError, ProtocolError
from devices.xray import XrayGenerator
from orbitct.orbits import Orbit
from tests.helpers.twin_process import twin_process

pytestmark = [pytest.mark.timeout(120), pytest.mark.system]


def console(proc: subprocess.Popen[str], line: str) -> str:
    """Send one console line; return the twin's answer."""
    assert proc.stdin is not None and proc.stderr is not None
    proc.stdin.write(line + "\n")
    proc.stdin.flush()
    return proc.stderr.readline().strip()


def test_carm_twin_command() -> None:
    with twin_process("carm", "--detector-size", "16", "--time-scale", "100", "--sag-deg", "2") as (port, proc):

        async def main() -> None:
            async with CArm("carm", f"tcp://127.0.0.1:{port}") as arm:
                await arm.load(export_program(Orbit("t", {}, np.radians([0.0, 3.0, 6.0]), np.zeros(3))))
                frames = await arm.run()
                assert [f.shape for f in frames] == [(16, 16)] * 3

        asyncio.run(main())


def test_xray_twin_command() -> None:
    with twin_process("xray", "--prep-ms", "10") as (port, proc):

        async def main() -> None:
            async with XrayGenerator("xray", f"modbus://127.0.0.1:{port}") as gen:
                assert await gen.expose() == 1
                assert console(proc, "door open") == "door open"
                with pytest.raises(InterlockOpenError):
                    await gen.expose()
                assert console(proc, "door closed") == "door closed"
                assert console(proc, "error 1") == "error next 1"
                with pytest.raises(ControllerError):
                    await gen.read()
                assert "not understood" in console(proc, "explode")
                assert await gen.expose() == 2
                assert console(proc, "misanswer 2") == "misanswer next 2"
                with pytest.raises(ProtocolError, match="another request"):
                    await gen.read()
                assert "not understood" in console(proc, "misanswer many")

        asyncio.run(main())


def test_carm_twin_rejects_bad_range() -> None:
    out = subprocess.run(
        [
            sys.executable,
            "-c",
            "from orbitct_app.cli.main import main; main()",
            "twin",
            "carm",
            "--primary-range-deg",
            "5",
            "1",
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode == 2 and "low (5) must be below high (1)" in out.stderr
