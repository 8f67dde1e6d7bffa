"""C-arm path: the orbit becomes a navigation program, played on the C-arm twin and recorded like a bench scan."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from acquire.config import CArmConfig, parse_config
from acquire.errors import PreflightError
from acquire.runner import ScanRequest, run_scan
from devices.carm_program import NavProgram
from orbitct.orbits import make_orbit
from orbitct.scanfile import ScanFile

pytestmark = [pytest.mark.timeout(120), pytest.mark.system]


def _config() -> CArmConfig:
    cfg = parse_config({"kind": "carm", "geometry": {"detector": {"rows": 64, "cols": 64}},
                        "calibration_frames": {"darks_before": 1, "flats_before": 1, "darks_after": 1, "flats_after": 1},
                        "sim": {"time_scale": 25.0}})
    assert isinstance(cfg, CArmConfig)
    return cfg


def test_carm_scan_records_program_frames_and_truth(tmp_path: Path) -> None:
    out = tmp_path / "carm.h5"
    params = {"start_deg": -180.0, "amplitude_deg": 10.0}
    res = run_scan(ScanRequest(config=_config(), out=out, orbit="sawtooth", frames=80, orbit_params=params, sim=True))
    assert res.status == "complete", res.reason
    orbit = make_orbit("sawtooth", n_frames=80, **params)
    program = NavProgram.read(out.with_suffix(".nav.json"))
    assert program.n_frames == 80 and NavProgram.read(out.with_suffix(".nav.csv")).n_frames == 80
    with ScanFile(out) as sf:
        assert sf.status == "complete" and sf.count_by_kind()["projection"] == 80
        proj = sf.projection_indices
        nominal = sf.geometry("nominal")[proj]
        assert nominal.allclose(_config().geometry.carm_views(orbit.theta, orbit.phi), atol_mm=1e-9)
        np.testing.assert_allclose(sf.axes("commanded")["carm.primary"][proj], orbit.theta_deg, atol=1e-9)
        assert np.isfinite(sf.axes("encoders")["carm.secondary"][proj]).all()
        # the C-arm twin's systematic errors show in the true geometry
        assert np.abs(sf.geometry("truth")[proj].S - nominal.S).max() > 1.0


def test_carm_orbit_outside_the_arm_range_is_refused(tmp_path: Path) -> None:
    out = tmp_path / "never.h5"
    with pytest.raises(PreflightError) as info:
        run_scan(ScanRequest(config=_config(), out=out, orbit="sawtooth", frames=80, sim=True))
    assert info.value.frame == 42 and "primary angle" in str(info.value)  # 0..360 deg leaves +-185 at 189 deg
    assert not out.exists()
