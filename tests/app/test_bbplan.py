"""The BB plan as the CLI and the REST service make it: real surfaces for the planner from a mesh, a NIfTI prior
volume, or a reconstruction in a scan file."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tests.calib.test_surfaces import _cylinder_mask


def test_load_surface_reads_a_mesh_a_nifti_volume_and_a_scan_files_reconstruction(tmp_path: Path) -> None:
    import trimesh

    from orbitct.geometry import VolumeGrid
    from orbitct.scanfile import ScanFile
    from orbitct_app.bbplan import BBPlanError, load_surface
    from recon.export import export_nifti
    from tests.helpers.service import write_small_scan

    mesh = trimesh.creation.cylinder(radius=60.0, height=80.0, sections=128)
    mesh.export(tmp_path / "object.stl")
    from_mesh = load_surface(str(tmp_path / "object.stl"))
    assert from_mesh.z_min_mm == pytest.approx(-40.0, abs=1.5) and from_mesh.z_max_mm == pytest.approx(40.0, abs=1.5)
    r = np.hypot(*from_mesh.points(np.linspace(0, 6, 20), np.zeros(20), 0.0)[:, :2].T)
    assert np.allclose(r, 60.0, atol=0.6), r

    mask, voxel, origin = _cylinder_mask()
    volume = np.where(mask, 0.02, 0.0).astype(np.float32) + np.random.default_rng(1).normal(
        0, 0.001, mask.shape
    ).astype(np.float32)
    grid = VolumeGrid(mask.shape, voxel, origin)
    export_nifti(volume, grid, tmp_path / "prior.nii.gz")
    from_volume = load_surface(str(tmp_path / "prior.nii.gz"))  # Otsu's threshold between air and object
    assert "prior.nii.gz >" in from_volume.describe()["source"]
    assert np.allclose(np.hypot(*from_volume.points(np.linspace(0, 6, 20), np.zeros(20), 0.0)[:, :2].T), 60.0, atol=1.0)

    scan = write_small_scan(tmp_path / "scan.h5")
    with ScanFile(scan, "r+") as sf:
        sf.write_recon(
            "prior",
            volume,
            voxel_mm=voxel,
            origin_mm=origin,
            algorithm="fdk",
            geometry="nominal",
            iterations=0,
            elapsed_s=0.1,
            params={},
        )
    from_scan = load_surface(f"{scan}#prior", threshold_per_mm=0.01)
    assert from_scan.radius_mm.shape == from_volume.radius_mm.shape
    for bad, message in (
        (str(tmp_path / "none.stl"), "no such file"),
        (str(scan), "expected a mesh"),
        (f"{scan}#nosuch", "no reconstruction 'nosuch'"),
    ):
        with pytest.raises(BBPlanError, match=message):
            load_surface(bad)
    with pytest.raises(BBPlanError, match="no voxel above the threshold"):
        load_surface(str(tmp_path / "prior.nii.gz"), threshold_per_mm=1.0)


def test_the_cli_plans_on_a_mesh(tmp_path: Path) -> None:
    import json

    import trimesh
    from click.testing import CliRunner

    from orbitct_app.cli.main import cli

    trimesh.creation.cylinder(radius=70.0, height=120.0, sections=96).export(tmp_path / "leg.stl")
    out = tmp_path / "plan.json"
    r = CliRunner().invoke(
        cli,
        [
            "plan",
            "bbs",
            "-e",
            "A",
            "--frames",
            "60",
            "--detector-size",
            "192",
            "--bbs",
            "6",
            "--surface",
            str(tmp_path / "leg.stl"),
            "--out",
            str(out),
        ],
    )
    assert r.exit_code == 0, r.output
    # how long it will take is said before the search, and how long it took after
    assert r.output.index("planning takes about") < r.output.index("wrote ") and "  time: " in r.output
    body = json.loads(out.read_text())
    assert body["surface"]["kind"] == "outline" and body["surface"]["source"] == "leg.stl"
    assert body["time"]["expected_s"] > 0 and body["time"]["elapsed_s"] > 0
    radii = [np.hypot(*b["xyz_mm"][:2]) for b in body["bbs"]]
    assert np.allclose(radii, 70.0 + body["bb_diameter_mm"] / 2, atol=1.0), radii
    bad = CliRunner().invoke(cli, ["plan", "bbs", "-e", "A", "--surface", str(tmp_path / "x.xyz"), "--out", str(out)])
    assert bad.exit_code == 1 and "no such file" in bad.output and "Traceback" not in bad.output
    bad = CliRunner().invoke(cli, ["plan", "bbs", "-e", "A", "--surface", "ellipsoid:70,60", "--out", str(out)])
    assert bad.exit_code == 1 and "expected ellipsoid:A,B,C" in bad.output and "Traceback" not in bad.output
    for zone, message in (("0:360,-500:500", "cover the whole surface"), ("30:30,-5:5", "no patch")):  # never a plan
        bad = CliRunner().invoke(
            cli,
            [
                "plan",
                "bbs",
                "-e",
                "A",
                "--frames",
                "20",
                "--detector-size",
                "64",
                "--keep-out",
                zone,
                "--out",
                str(tmp_path / "k.json"),
            ],
        )
        assert bad.exit_code != 0 and message in bad.output and "Traceback" not in bad.output, bad.output


def test_a_plan_on_an_elliptic_object_gives_the_polar_angles_a_person_measures(tmp_path: Path) -> None:
    """Experiment C's torso is an elliptic cylinder (120 by 90 mm): each BB's angle is the polar angle of its place
    (where the ellipse's parameter is up to 8 degrees off), and none lies in the keep-out patch, in polar angles."""
    import json

    from click.testing import CliRunner

    from orbitct_app.cli.main import cli

    out = tmp_path / "plan.json"
    r = CliRunner().invoke(
        cli,
        [
            "plan",
            "bbs",
            "-e",
            "C",
            "--frames",
            "40",
            "--detector-size",
            "128",
            "--bbs",
            "8",
            "--keep-out",
            "20:70,-100:100",
            "--out",
            str(out),
        ],
    )
    assert r.exit_code == 0, r.output
    bbs = json.loads(out.read_text())["bbs"]
    polar = np.array([np.degrees(np.arctan2(b["xyz_mm"][1], b["xyz_mm"][0])) % 360.0 for b in bbs])
    assert np.allclose([b["angle_deg"] for b in bbs], polar, atol=0.3), ([b["angle_deg"] for b in bbs], polar)
    assert not ((polar >= 20.0) & (polar <= 70.0)).any(), polar


@pytest.mark.parametrize(
    ("body", "needle"),
    [
        ("not json", "not JSON"),
        ("[1, 2]", "not a BB plan"),
        ('{"bbs": [{"xyz_mm": [70, 0, 0]}]}', "bb_diameter_mm must be a number"),
        ('{"bb_diameter_mm": -3, "bbs": [{"xyz_mm": [70, 0, 0]}]}', "bb_diameter_mm must be a number"),
        ('{"bb_diameter_mm": 3, "bbs": []}', "1 to 40 BBs"),
        ('{"bb_diameter_mm": 3, "bbs": [{"xyz_mm": [1, 2]}]}', "BB 1 needs xyz_mm as three numbers"),
        ('{"bb_diameter_mm": 3, "bbs": [{"xyz_mm": [70, 0, 0]}, {"xyz_mm": ["a", 0, 0]}]}', "BB 2 needs xyz_mm"),
        ('{"bb_diameter_mm": 3, "bbs": [{"xyz_mm": [NaN, 0, 0]}]}', "not within 500 mm"),
        ('{"bb_diameter_mm": 3, "bbs": [{"xyz_mm": [1e9, 0, 0]}]}', "not within 500 mm"),
        ('{"bb_diameter_mm": 3, "bbs": [{"xyz_mm": [70, 0, 0]}, {"xyz_mm": [71, 0, 0]}]}', "cannot overlap"),
        (
            '{"experiment": "C", "bb_diameter_mm": 3, "bbs": [{"xyz_mm": [70, 0, 0]}]}',
            "planned for experiment C, not A",
        ),
    ],
)
def test_simulate_refuses_a_plan_file_that_is_not_one_in_one_line(tmp_path: Path, body: str, needle: str) -> None:
    """``orbitct simulate --bbs-from``: a plan written by hand or damaged is refused naming what is wrong, before
    anything is imaged; never a traceback, never a scan of BBs the file did not mean."""
    from click.testing import CliRunner

    from orbitct_app.cli.main import cli

    plan, out = tmp_path / "plan.json", tmp_path / "x.h5"
    plan.write_text(body)
    r = CliRunner().invoke(
        cli,
        ["simulate", "-e", "A", "--frames", "10", "--detector-size", "32", "--bbs-from", str(plan), "--out", str(out)],
    )
    assert r.exit_code == 2 and needle in r.output and "Traceback" not in r.output, r.output
    assert not out.exists()


def test_the_plans_expected_time_is_said_before_the_search_starts() -> None:
    from orbitct.progress import ProgressEvent
    from orbitct_app.bbplan import BBPlanRequest, make_bb_plan

    events: list[ProgressEvent] = []
    plan = make_bb_plan(BBPlanRequest.checked(experiment="B", frames=40, detector_px=128, bbs=5), events.append)
    stages = [e.stage for e in events]
    assert stages[0] == "prepare" and stages.count("duration") == 1  # said before the search, after preparing
    assert stages.index("prepare") < stages.index("duration") < stages.index("plan")
    said = events[stages.index("duration")]
    assert said.metrics["expected_s"] == pytest.approx(plan.body["time"]["expected_s"], abs=0.01)
    assert said.message.startswith("planning takes about ") and said.message.endswith(" on this machine now")
    # looking for the fewest BBs: the bound is said as one
    events.clear()
    make_bb_plan(
        BBPlanRequest.checked(experiment="B", frames=40, detector_px=128, target_px=5.0, max_bbs=5), events.append
    )
    assert next(e.message for e in events if e.stage == "duration").startswith("planning takes at most about ")
