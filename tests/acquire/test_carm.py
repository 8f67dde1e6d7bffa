"""C-arm path: the orbit becomes a navigation program, played on the C-arm twin and recorded like a bench scan."""

from __future__ import annotations

import asyncio
from pathlib import Path

import numpy as np
import pytest

from acquire.config import CArmConfig, StallConfig, parse_config
from acquire.errors import PreflightError
from acquire.rigs.carm import open_carm
from acquire.runner import ScanRequest, ScanResult, ScanRunner, run_scan
from devices.carm_program import NavProgram
from devices.sim import twin_of
from orbitct.orbits import make_orbit
from orbitct.scanfile import ScanFile

pytestmark = [pytest.mark.timeout(120), pytest.mark.system]


def _config() -> CArmConfig:
    cfg = parse_config(
        {
            "kind": "carm",
            "geometry": {"detector": {"rows": 64, "cols": 64}},
            "calibration_frames": {"darks_before": 1, "flats_before": 1, "darks_after": 1, "flats_after": 1},
            "sim": {"time_scale": 25.0},
        }
    )
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


def test_carm_asks_its_rig_kind_for_modes_and_refuses_injected_errors(tmp_path: Path) -> None:
    """What differs from the bench comes from the rig's kind: step scans only, its own errors are what is measured."""
    from acquire.errors import AcquireError
    from acquire.rigs import rig_kind
    from acquire.runner import build_plan

    cfg = _config()
    kind = rig_kind(cfg)
    assert kind.name == "C-arm" and kind.modes == ("step",) and not kind.injects_errors
    request = ScanRequest(config=cfg, out=tmp_path / "never.h5", orbit="sawtooth", frames=40, mode="continuous")
    with pytest.raises(AcquireError, match="the C-arm runs scans in mode 'step', not 'continuous'"):
        build_plan(request, cfg)
    params = {"start_deg": -180.0, "amplitude_deg": 10.0}
    plan = build_plan(
        ScanRequest(
            config=cfg, out="unused.h5", orbit="sawtooth", frames=80, orbit_params=params, errors="bench", seed=3
        ),
        cfg,
    )
    assert not plan.errors.any()  # asked-for errors are not injected into a C-arm


def test_carm_that_stops_delivering_frames_ends_the_scan_as_a_stall(tmp_path: Path) -> None:
    cfg = _config().model_copy(update={"stall": StallConfig(frame_s=1.0, exposure_s=0.5)})
    out = tmp_path / "stall.h5"
    req = ScanRequest(
        config=cfg,
        out=out,
        orbit="sawtooth",
        frames=80,
        orbit_params={"start_deg": -180.0, "amplitude_deg": 10.0},
        sim=True,
    )

    async def main() -> ScanResult:
        async with open_carm(cfg, sim=True) as rig:
            twin_of(rig.carm).readout_s = 25.0
            result = await ScanRunner(req, rig=rig).run()
            assert await rig.carm.on_target()  # halted, not on its way anywhere
            return result

    res = asyncio.run(main())
    assert res.status == "aborted" and res.reason.startswith("stall: carm delivered no")
    assert "stall.frame_s" in res.reason
    with ScanFile(out) as sf:
        assert sf.status == "aborted" and sf.status_reason.startswith("stall: carm")
