"""C-arm: orbit -> navigation program (CSV/JSON, refusals), and the driver playing it on the C-arm twin."""

from __future__ import annotations

import asyncio
import itertools
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from devices.carm import CArm
from devices.carm_program import (
    CArmLimits,
    InfeasibleOrbitError,
    NavPoint,
    NavProgram,
    ProgramFileError,
    export_program,
)
from devices.errors import (
    ControllerError,
    DeviceTimeoutError,
    NotConnectedError,
    OutOfLimitsError,
    ProtocolError,
)
from devices.factory import opened
from devices.sim import twin_of
from devices.twins.carm import CArmTwin
from devices.twins.runtime import TwinThread
from orbitct.geometry import ViewGeometry
from orbitct.orbits import Orbit

pytestmark = [pytest.mark.timeout(120), pytest.mark.system]
_worlds = itertools.count()


def orbit(theta_deg: Any, phi_deg: Any, segment: Any = None) -> Orbit:
    return Orbit("test", {"k": 1}, np.radians(theta_deg), np.radians(phi_deg), segment)


def test_export_points_follow_the_orbit() -> None:
    o = orbit(np.linspace(-20, 20, 11), 5 * np.sin(np.linspace(0, np.pi, 11)))
    prog = export_program(o, CArmLimits(isocenter_mm=(1.0, 2.0, 3.0)), speed_deg_s=15.0)
    assert len(prog) == 11 and prog.n_frames == 11
    np.testing.assert_allclose([p.primary_deg for p in prog.points], np.linspace(-20, 20, 11))
    assert all(p.isocenter_mm == (1.0, 2.0, 3.0) and p.speed_deg_s == 15.0 and p.acquire for p in prog.points)
    assert prog.orbit == {"name": "test", "params": {"k": 1}}


def test_segments_are_bridged_within_max_step() -> None:
    o = orbit([0, 2, 4, 40, 42], [0, 0, 0, 10, 10], [0, 0, 0, 1, 1])
    prog = export_program(o, CArmLimits(max_step_deg=5.0))
    assert prog.n_frames == 5 and len(prog) > 5
    steps = np.abs(np.diff([[p.primary_deg, p.secondary_deg] for p in prog.points], axis=0)).max(axis=1)
    assert steps.max() <= 5.0 + 1e-9
    assert [p.index for p in prog.points] == list(range(len(prog)))


def test_infeasible_orbits_name_the_first_bad_frame() -> None:
    with pytest.raises(InfeasibleOrbitError, match="orbit frame 2: secondary angle 60.000 deg") as err:
        export_program(orbit([0, 1, 2, 3], [0, 0, 60, 70]))
    assert err.value.index == 2
    with pytest.raises(InfeasibleOrbitError, match="orbit frame 1: primary angle 190") as err:
        export_program(orbit([180, 190], [0, 0]), CArmLimits(max_step_deg=20))
    with pytest.raises(InfeasibleOrbitError, match="frame 3: step of 8.000 deg") as err:
        export_program(orbit([0, 1, 2, 10], [0, 0, 0, 0]), CArmLimits(max_step_deg=5))
    assert err.value.index == 3
    with pytest.raises(ValueError, match="speed_deg_s"):
        export_program(orbit([0], [0]), CArmLimits(max_speed_deg_s=30), speed_deg_s=45)


@pytest.mark.parametrize("suffix", [".csv", ".json"])
def test_program_files_round_trip(tmp_path: Path, suffix: str) -> None:
    o = orbit([0, 3, 20, 23], [0, 1, 2, 3], [0, 0, 1, 1])
    prog = export_program(o, CArmLimits(max_step_deg=4.0, isocenter_mm=(0.5, 0, -1)))
    back = NavProgram.read(prog.write(tmp_path / f"prog{suffix}"))
    assert back.limits == prog.limits and back.orbit == prog.orbit and len(back) == len(prog)
    for a, b in zip(prog.points, back.points):
        assert a.index == b.index and a.acquire == b.acquire and a.segment == b.segment
        assert math.isclose(a.primary_deg, b.primary_deg, abs_tol=1e-6) and a.isocenter_mm == pytest.approx(
            b.isocenter_mm
        )


def test_bad_program_files(tmp_path: Path) -> None:
    bad = tmp_path / "bad.csv"
    bad.write_text(
        "index,segment,primary_deg,secondary_deg,iso_x_mm,iso_y_mm,iso_z_mm,speed_deg_s,acquire\n0,0,1,2,0,0,0,10,maybe\n"
    )
    with pytest.raises(ProgramFileError, match="bad.csv:2"):
        NavProgram.read(bad)
    bad.write_text("a,b\n")
    with pytest.raises(ProgramFileError, match="header row"):
        NavProgram.read(bad)
    js = tmp_path / "bad.json"
    js.write_text('{"format": "something"}')
    with pytest.raises(ProgramFileError, match="format"):
        NavProgram.read(js)
    with pytest.raises(ProgramFileError, match=r"\.csv or \.json"):
        export_program(orbit([0], [0])).write(tmp_path / "p.txt")


def run(body: Any, **options: Any) -> Any:
    options.setdefault("rows", 32)
    options.setdefault("time_scale", 100.0)
    options.setdefault("timeout_s", 1.0)
    world = f"carmtest{next(_worlds)}"

    async def main() -> Any:
        async with opened("carm", "carm", f"sim://{world}", **options) as arm:
            return await body(arm)

    return asyncio.run(main())


def test_play_program_frames_carry_true_geometry_with_errors() -> None:
    o = orbit(np.linspace(-10, 10, 5), np.linspace(0, 8, 5))
    prog = export_program(o)

    async def body(arm: CArm) -> tuple[list[Any], list[float]]:
        info = await arm.describe()
        assert [a.name for a in info.axes] == ["primary", "secondary"] and info.axes[1].high == 50.0
        await arm.load(prog)
        reports: list[float] = []
        status = arm.run()
        status.watch(lambda p: reports.append(p.fraction))
        frames = await status
        assert (await arm.position())["primary"] == pytest.approx(10.0)
        return frames, reports

    frames, reports = run(body, sag_deg=1.0, drift_mm=3.0, eta_deg=0.7, primary_offset_deg=0.4, noise_mm=0.0)
    assert len(frames) == 5 and [f.meta["point"] for f in frames] == [0, 1, 2, 3, 4] and reports[-1] == 1.0
    assert all(f.shape == (32, 32) and f.data.dtype == np.uint16 for f in frames)
    nominal = o.nominal_geometry(785.0, 1200.0, CArmTwin(rows=32).geometry)
    truth = np.array([f.meta["truth_vectors"] for f in frames])
    # the true geometry follows the documented error model exactly (noise off)
    th, ph = np.radians(np.linspace(-10, 10, 5)), np.radians(np.linspace(0, 8, 5))
    shift = 3.0 * np.stack([np.sin(th), 0.5 * np.sin(2 * th), 0.5 * (1 - np.cos(th))], 1)
    expected = ViewGeometry.from_carm(
        th + np.radians(0.4),
        ph - np.radians(1.0) * np.cos(th) * np.cos(ph),
        785.0,
        1200.0,
        nominal.panel,
        eta=np.radians(0.7),
        shift=shift,
    )
    np.testing.assert_allclose(truth, expected.vectors, atol=1e-9)
    assert np.abs(truth - nominal.vectors).max() > 1.0  # the errors are real
    # the source really moves between frames (object fixed)
    assert np.linalg.norm(truth[0, :3] - truth[-1, :3]) > 100


def test_move_goto_expose_and_refusals() -> None:
    prog = export_program(orbit([0, 4, 8], [0, 0, 0]))

    async def body(arm: CArm) -> None:
        await arm.move({"primary": 20.0, "secondary": -5.0})
        assert await arm.position() == pytest.approx({"primary": 20.0, "secondary": -5.0})
        assert await arm.on_target()
        with pytest.raises(OutOfLimitsError, match="secondary angle 70.000"):
            await arm.move({"secondary": 70.0})
        assert (await arm.position())["secondary"] == pytest.approx(-5.0)
        await arm.load(prog)
        await arm.goto(2)
        frame = await arm.expose()
        assert frame.meta["point"] == 2 and frame.meta["primary_deg"] == pytest.approx(8.0)
        bad = NavProgram((NavPoint(0, 0, 0.0, 80.0, (0.0, 0.0, 0.0), 10.0, True),), CArmLimits(secondary_deg=(-90, 90)))
        with pytest.raises(OutOfLimitsError, match="program point 0"):
            await arm.load(bad)
        with pytest.raises(ControllerError, match="not in the program"):
            await arm.goto(7)
        state = await arm.read()
        assert state["point"] == 2 and not state["moving"]

    run(body)


def test_faults_on_the_carm_link() -> None:
    async def body(arm: CArm) -> None:
        twin_of(arm).faults.drop_next = 1
        assert "primary" in await arm.position()  # safe query reconnects
        twin_of(arm).faults.match, twin_of(arm).faults.drop_next = "MOVE", 1
        with pytest.raises(NotConnectedError):
            await arm.move({"primary": 5.0})  # a move is never repeated blindly
        assert sum(c.startswith("MOVE") for c in twin_of(arm).commands_seen) == 1
        twin_of(arm).faults.match = ""
        twin_of(arm).faults.error_next = 1
        with pytest.raises(ControllerError):
            await arm.position()
        await arm.load(export_program(orbit([0, 2, 4], [0, 0, 0])))
        twin_of(arm).faults.missing_frame_next = 1
        with pytest.raises(DeviceTimeoutError, match="frame.* missing"):
            await arm.run()  # the first frame never arrives: named by the gap
        twin_of(arm).faults.latency_s = 0.5
        with pytest.raises(DeviceTimeoutError, match="no reply"):
            await arm.position()
        twin_of(arm).faults.latency_s = 0.0
        await asyncio.sleep(0.6)
        twin_of(arm).faults.garble_next = 1
        with pytest.raises(ProtocolError):
            await arm._l().command("POS?", retry=False)
        twin_of(arm).stuck = True
        with pytest.raises(DeviceTimeoutError, match="stuck at primary"):
            await arm.move({"primary": 30.0})
        assert (
            sum(c.startswith("MOVE") for c in twin_of(arm).commands_seen) == 2 and "STOP" in twin_of(arm).commands_seen
        )
        twin_of(arm).stuck = False
        await arm.move({"primary": 1.0})
        assert (await arm.position())["primary"] == pytest.approx(1.0)

    run(body, stall_s=0.3, timeout_s=0.3)


def test_standalone_carm_twin_over_tcp() -> None:
    twin = CArmTwin(rows=16, time_scale=100.0)
    thread = TwinThread(twin)
    try:

        async def main() -> None:
            async with CArm("carm", f"tcp://127.0.0.1:{thread.port}") as arm:
                await arm.load(export_program(orbit([0, 2], [0, 0])))
                assert len(await arm.run()) == 2

        asyncio.run(main())
    finally:
        thread.stop()


def test_stop_during_a_run_is_immediate() -> None:
    prog = export_program(orbit(np.arange(0.0, 100.0, 4.0), np.zeros(25)), speed_deg_s=10.0)

    async def body(arm: CArm) -> None:
        await arm.load(prog)
        status = arm.run()
        await asyncio.sleep(0.3)
        t0 = asyncio.get_running_loop().time()
        await arm.stop()  # while run() waits for its next frame on the main link
        assert asyncio.get_running_loop().time() - t0 < 2.0  # not queued behind the frame wait (30 s)
        status.cancel()
        p0 = (await arm.position())["primary"]
        await asyncio.sleep(0.2)
        assert (await arm.position())["primary"] == p0 and not (await arm.read())["moving"]
        # cancelling a move (an abort) stops the arm too
        move = arm.move({"primary": 90.0})
        await asyncio.sleep(0.2)
        move.cancel()
        with pytest.raises(asyncio.CancelledError):
            await move
        await asyncio.sleep(0.05)
        assert twin_of(arm).commands_seen.count("STOP") == 3  # explicit stop, cancelled run, cancelled move
        p0 = (await arm.position())["primary"]
        await asyncio.sleep(0.2)
        assert (await arm.position())["primary"] == p0 and not (await arm.read())["moving"]
        assert p0 < 96.0

    run(body, time_scale=1.0)


def test_last_frame_missing_is_named_when_the_program_ends() -> None:
    async def body(arm: CArm) -> None:
        await arm.load(export_program(orbit([0, 2], [0, 0])))
        frames = await arm.run()
        twin_of(arm).faults.match, twin_of(arm).faults.missing_frame_next = f"frame {frames[-1].number + 2};", 1
        with pytest.raises(DeviceTimeoutError, match="1 of 2 frames"):
            await arm.run()

    run(body)
