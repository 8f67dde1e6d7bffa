"""Plans are pure data; pre-flight refuses infeasible orbits naming the first offending frame and axis."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from acquire.config import parse_config
from acquire.errors import PreflightError
from acquire.plan import plan_bench_scan
from acquire.preflight import bench_preflight
from orbitct.scanfile.keys import ImageKey

CFG = parse_config(
    {
        "geometry": {"detector": {"rows": 64, "cols": 64}},
        "calibration_frames": {"darks_before": 2, "flats_before": 3, "darks_after": 1, "flats_after": 1},
    }
)


def _sawtooth(n: int = 40, tilt_deg: float = 20.0) -> tuple[np.ndarray, np.ndarray]:
    theta = np.linspace(0, 2 * np.pi, n, endpoint=False)
    phase = (theta / (2 * np.pi) * 2 * 2) % 2
    phi = np.radians(tilt_deg) * np.where(phase < 1, 2 * phase - 1, 3 - 2 * phase)
    return theta, phi


def test_plan_layout_and_nominal_geometry() -> None:
    theta, phi = _sawtooth()
    plan = plan_bench_scan(CFG, theta, phi, orbit_name="sawtooth", orbit_params={"n": 40})
    assert plan.n_frames == 40 + 7 and plan.n_projections == 40
    assert list(plan.image_key[:5]) == [ImageKey.DARK, ImageKey.DARK, ImageKey.FLAT, ImageKey.FLAT, ImageKey.FLAT]
    assert list(plan.image_key[-2:]) == [ImageKey.DARK, ImageKey.FLAT]
    proj = plan.image_key == ImageKey.PROJECTION
    assert plan.nominal[np.flatnonzero(proj)].allclose(CFG.geometry.carm_views(theta, phi))
    assert np.isnan(plan.nominal.vectors[~proj]).all()
    # darks/flats sit at the first / last projection pose
    for axis, values in plan.targets.items():
        assert values[0] == values[5] and values[-1] == values[-3], axis
    assert plan.frame(5).kind == "projection" and plan.frame(5).view == 0


def test_feasible_orbit_passes() -> None:
    theta, phi = _sawtooth()
    asyncio.run(bench_preflight(plan_bench_scan(CFG, theta, phi), CFG))


def test_tilt_beyond_hexapod_limit_is_refused_at_first_frame() -> None:
    theta, phi = _sawtooth(tilt_deg=35.0)
    plan = plan_bench_scan(CFG, theta, phi)
    with pytest.raises(PreflightError) as info:
        asyncio.run(bench_preflight(plan, CFG))
    first = int(np.flatnonzero(np.abs(plan.targets["hexapod.U"]) > 30)[0])
    assert info.value.frame == first and info.value.axis == "hexapod.U"
    assert f"frame {first}" in str(info.value) and "nothing moved" in str(info.value)


def test_errors_push_translation_out_of_range() -> None:
    theta, phi = _sawtooth()
    err = np.zeros((theta.size, 6))
    err[17, 5] = 30.0  # z shift beyond the +-25 mm range
    with pytest.raises(PreflightError) as info:
        asyncio.run(bench_preflight(plan_bench_scan(CFG, theta, phi, err), CFG))
    assert info.value.frame == 17 + 5 and info.value.axis == "hexapod.Z"
    assert "nothing moved. The targets include the plan's injected motion errors" in str(info.value)


def test_a_refusal_caused_with_the_bench_error_profile_says_so() -> None:
    """DCArc (tilts up to 29 deg) at 120 frames: the bench profile's errors, as large as a step per frame, take the
    tilt past the hexapod's 30 deg; the refusal says the errors are part of the targets and what may pass."""
    from pathlib import Path

    from acquire.config import load_config
    from acquire.runner import ScanRequest, build_plan

    cfg = load_config(Path(__file__).resolve().parents[2] / "config" / "bench.yaml").with_detector_size(32)

    def plan(errors: str):  # type: ignore[no-untyped-def]
        return build_plan(ScanRequest(config=cfg, out="unused.h5", orbit="dcarc", frames=120, errors=errors), cfg)

    with pytest.raises(PreflightError, match="hexapod.U") as info:
        asyncio.run(bench_preflight(plan("bench"), cfg))
    assert "the 'bench' error profile's injected motion errors" in str(info.value)
    assert "fewer frames, larger errors" in str(info.value)
    asyncio.run(bench_preflight(plan("none"), cfg))


def test_controller_limits_are_checked_too() -> None:
    theta, phi = _sawtooth()
    plan = plan_bench_scan(CFG, theta, phi)
    with pytest.raises(PreflightError, match="controller range") as info:
        asyncio.run(bench_preflight(plan, CFG, device_limits={"rotation_stage.R": (-180.0, 180.0)}))
    assert info.value.axis == "rotation_stage.R"
    assert plan.targets["rotation_stage.R"][info.value.frame] < -180


def test_workspace_check_refusal_names_the_frame() -> None:
    theta, phi = _sawtooth()
    plan = plan_bench_scan(CFG, theta, phi)

    async def refuse_tilts_over_15(poses):  # the check the controller's VMO? answers
        return next((i for i, p in enumerate(poses) if abs(p["U"]) > 15), None)

    with pytest.raises(PreflightError, match="workspace") as info:
        asyncio.run(bench_preflight(plan, CFG, workspace_check=refuse_tilts_over_15))
    assert abs(plan.targets["hexapod.U"][info.value.frame]) > 15


def test_continuous_mode_speed_limit() -> None:
    theta, phi = _sawtooth(n=40)
    plan = plan_bench_scan(CFG, theta, phi)
    asyncio.run(bench_preflight(plan, CFG, mode="continuous", frame_rate_hz=5))
    with pytest.raises(PreflightError, match="velocity"):
        asyncio.run(bench_preflight(plan, CFG, mode="continuous", frame_rate_hz=1000))


def test_continuous_mode_checks_each_sweeps_run_up_against_the_stage_range() -> None:
    """A sweep starts a little before its first trigger angle and runs a little past its last one, so it is at speed
    when it passes them; where that leaves the stage's range the scan is refused before anything moves (the
    stage had turned 2.25 degrees past the configured range unchecked, and the scan completed)."""
    from acquire.plan import SWEEP_RUN_UP_S, sweeps

    theta, phi = _sawtooth(n=40)
    plan = plan_bench_scan(CFG, theta, phi)
    stage = plan.targets["rotation_stage.R"]  # the stage turns -theta: 0 down to -351 deg
    ((start, end),) = sweeps(plan)
    assert stage[start] == 0.0 and stage[end] == pytest.approx(-351.0)
    tight = CFG.model_copy(update={"limits": CFG.limits.model_copy(update={"rotation_stage_deg": (-352.0, 0.5)})})
    asyncio.run(bench_preflight(plan, tight, mode="step"))  # every trigger angle is inside
    asyncio.run(bench_preflight(plan, tight, mode="continuous", frame_rate_hz=0.5))  # runs up 0.2 deg: inside
    with pytest.raises(
        PreflightError,
        match=r"frame 5: axis rotation_stage.R \(run-up before the sweep's trigger "
        r"angle at 5 frames/s\) = 2.25 deg is outside the configured range",
    ):
        asyncio.run(bench_preflight(plan, tight, mode="continuous", frame_rate_hz=5))  # 45 deg/s: 2.25 deg
    assert pytest.approx(2.25) == 45.0 * SWEEP_RUN_UP_S
    wide = CFG.model_copy(update={"limits": CFG.limits.model_copy(update={"rotation_stage_deg": (-352.0, 3.0)})})
    with pytest.raises(PreflightError, match="run-on past the sweep's trigger angle"):
        asyncio.run(bench_preflight(plan, wide, mode="continuous", frame_rate_hz=5))  # -351 - 2.25 < -352


def test_continuous_mode_counts_no_speed_for_the_rewind_between_two_turns() -> None:
    """DCArc: two turns (the stage rewound by 357 deg between them) and a tilt-only arc. The rewind and the arc are
    moves of their own; only steps made while the stage sweeps between triggers are held to the frame rate."""
    from pathlib import Path

    from acquire.config import load_config
    from acquire.plan import swept_steps
    from acquire.runner import ScanRequest, build_plan

    cfg = load_config(Path(__file__).resolve().parents[2] / "config" / "bench.yaml").with_detector_size(32)
    plan = build_plan(ScanRequest(config=cfg, out="unused.h5", orbit="dcarc", frames=300), cfg)
    swept, stage = swept_steps(plan), plan.targets["rotation_stage.R"]
    rewind = int(np.argmax(np.diff(stage)))
    assert np.diff(stage)[rewind] > 350 and not swept[rewind] and swept[rewind - 1] and swept[rewind + 1]
    assert not swept[: int(np.flatnonzero(plan.image_key == ImageKey.PROJECTION)[0])].any()  # to and from darks/flats
    asyncio.run(bench_preflight(plan, cfg, mode="continuous", frame_rate_hz=10))  # 26 deg/s while sweeping
    with pytest.raises(PreflightError, match="rotation_stage velocity"):
        asyncio.run(bench_preflight(plan, cfg, mode="continuous", frame_rate_hz=50))  # 129 deg/s: too fast


def test_sweeps_split_where_the_stage_stops_or_reverses() -> None:
    from acquire.plan import sweep_end

    stage = np.array([0.0, -1, -2, -3, -3, -3, -2, -1, 0])
    assert sweep_end(stage, 0, 8) == 3  # turns one way until frame 3
    assert sweep_end(stage, 3, 8) == 3 and sweep_end(stage, 4, 8) == 4  # stays: step and shoot
    assert sweep_end(stage, 5, 8) == 8  # reverses and turns to the end
    assert sweep_end(stage, 8, 8) == 8


@pytest.mark.system
@pytest.mark.parametrize("orbit, params", [("sawtooth", {}), ("dcarc", {}), ("multiarc", {"preset": "pheno"})])
@pytest.mark.parametrize("errors", ["none", "bench"])
def test_the_default_bench_runs_every_published_orbit(orbit: str, params: dict, errors: str) -> None:
    """The three orbits of the published study pass pre-flight on config/bench.yaml (its twins' controllers)."""
    from pathlib import Path

    from acquire.config import load_config
    from acquire.rigs.bench import open_bench
    from acquire.runner import ScanRequest, build_plan

    cfg = load_config(Path(__file__).resolve().parents[2] / "config" / "bench.yaml").with_detector_size(32)
    cfg = cfg.model_copy(update={"sim": cfg.sim.model_copy(update={"time_scale": 50.0})})
    plan = build_plan(ScanRequest(config=cfg, out="unused.h5", orbit=orbit, orbit_params=params, errors=errors), cfg)

    async def main() -> None:
        async with open_bench(cfg, sim=True) as rig:
            await rig.preflight(plan, "step", cfg.exposure.frame_rate_hz)

    asyncio.run(main())


def test_a_panel_that_delivers_frames_of_another_size_is_refused_before_anything_moves() -> None:
    """The configuration (or --detector-size) and the connected panel disagree on the frame size: refused at pre-flight,
    naming both sizes; it had surfaced at the first frame, after the move to the first pose."""
    from pathlib import Path

    from acquire.config import load_config
    from acquire.errors import RefusedError
    from acquire.rigs.bench import open_bench
    from acquire.runner import ScanRequest, build_plan

    cfg = load_config(Path(__file__).resolve().parents[2] / "config" / "bench.yaml").with_detector_size(32)
    other = cfg.with_detector_size(48)
    plan = build_plan(ScanRequest(config=other, out="unused.h5", orbit="sawtooth", frames=20), other)

    async def main() -> None:
        async with open_bench(cfg, sim=True) as rig:
            with pytest.raises(RefusedError, match="delivers 32 x 32 px frames, the plan records 48 x 48"):
                await rig.preflight(plan, "step", cfg.exposure.frame_rate_hz)

    asyncio.run(main())
