"""``orbitct twin carm`` and ``orbitct twin xray`` as separate processes, driven over TCP."""

from __future__ import annotations

import asyncio
import re
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np
import pytest

from devices.carm import CArm, export_program
from devices.xray import XrayGenerator
from orbitct.orbits import Orbit

pytestmark = pytest.mark.timeout(120)


@contextmanager
def twin_process(*args: str) -> Iterator[int]:
    """Start ``orbitct twin ARGS --port 0``; yield the port it printed."""
    cmd = [sys.executable, "-c", "from orbitct.cli.main import main; main()", "twin", *args, "--port", "0"]
    proc = subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stderr is not None
        line = proc.stderr.readline()
        match = re.search(r"127\.0\.0\.1:(\d+)", line)
        assert match, f"no port in {line!r}"
        yield int(match.group(1))
    finally:
        proc.terminate()
        proc.wait(10)


def test_carm_twin_command() -> None:
    with twin_process("carm", "--detector-size", "16", "--time-scale", "100", "--sag-deg", "2") as port:

        async def main() -> None:
            async with CArm("carm", f"tcp://127.0.0.1:{port}") as arm:
                await arm.load(export_program(Orbit("t", {}, np.radians([0.0, 3.0, 6.0]), np.zeros(3))))
                frames = await arm.run()
                assert [f.shape for f in frames] == [(16, 16)] * 3

        asyncio.run(main())


def test_xray_twin_command() -> None:
    with twin_process("xray", "--prep-ms", "10") as port:

        async def main() -> None:
            async with XrayGenerator("xray", f"modbus://127.0.0.1:{port}") as gen:
                assert await gen.expose() == 1

        asyncio.run(main())


def test_carm_twin_rejects_bad_range() -> None:
    out = subprocess.run(
        [sys.executable, "-c", "from orbitct.cli.main import main; main()", "twin", "carm", "--primary-range-deg", "5", "1"],
        capture_output=True, text=True, timeout=60,
    )
    assert out.returncode == 2 and "low (5) must be below high (1)" in out.stderr
