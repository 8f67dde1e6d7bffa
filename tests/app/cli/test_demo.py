"""``orbitct demo`` end to end at a small size: scan on the twins, calibration, reconstruction."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from click.testing import CliRunner

from orbitct.scanfile import ScanFile
from orbitct_app.cli.main import cli

pytestmark = pytest.mark.system


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_demo_small(tmp_path: Path) -> None:
    out = tmp_path / "demo"
    result = CliRunner().invoke(cli, ["demo", "--out", str(out), "--frames", "90", "--size", "256", "--voxels", "32"])
    assert result.exit_code == 0, result.output
    assert "complete: 102 frames" in result.output
    scan = out / "experiment-a.h5"
    with ScanFile(scan) as sf:
        assert sf.status == "complete" and sf.has_geometry("truth")
        if sf.has_geometry("calibrated"):  # calibration and reconstruction are guarded when not installed
            m = re.search(r"calibrated ([0-9.]+) mm", result.output)
            assert m is not None and float(m.group(1)) < 1.0
            assert "fdk_calibrated" in sf.recon_names()
    assert (out / "recon" / "comparison.png").read_bytes()[:4] == b"\x89PNG"
    assert "calibrated next to nominal, one grey window" in result.output
    assert "inspect it with:" in result.output and "orbitct inspect" in result.output
