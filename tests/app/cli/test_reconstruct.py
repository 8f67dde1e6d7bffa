"""The ``orbitct reconstruct`` command."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from click.testing import CliRunner

from orbitct.geometry import ViewGeometry
from orbitct.scanfile import ScanFile
from orbitct_app.cli.main import cli
from tests.helpers.recon import bench_detector, write_sphere_scan


def test_cli_reconstructs_and_reports_errors(tmp_path: Path) -> None:
    g = ViewGeometry.from_carm(np.linspace(0, 2 * np.pi, 40, endpoint=False), 0.0, 785.0, 1200.0, bench_detector(48))
    path = tmp_path / "s.h5"
    write_sphere_scan(path, g)
    runner = CliRunner()
    res = runner.invoke(
        cli,
        [
            "reconstruct",
            str(path),
            "--algorithm",
            "pwls",
            "--geometry",
            "nominal",
            "--shape",
            "24,40,40",
            "--voxel-mm",
            "3",
            "--iterations",
            "3",
            "--export",
            "png",
            "--name",
            "cli",
            "--stream",
            "file",
        ],
    )
    assert res.exit_code == 0, res.output
    assert "/recon/cli" in res.output and "cost" in res.output and "s_cli_axial.png" in res.output
    with ScanFile(path) as sf:
        assert sf.read_recon("cli")[0].shape == (24, 40, 40)
    bad = runner.invoke(cli, ["reconstruct", str(path), "--geometry", "calibrated"])
    assert bad.exit_code != 0 and "no calibrated geometry" in bad.output
    bad = runner.invoke(cli, ["reconstruct", str(path), "--geometry", "nominal", "--stream", "disk"])
    assert bad.exit_code != 0 and "auto" in bad.output and "file" in bad.output
    bad = runner.invoke(cli, ["reconstruct", str(path), "--geometry", "nominal", "--shape", "10,10"])
    assert bad.exit_code != 0 and "NZ,NY,NX" in bad.output


def test_compare_puts_two_geometries_side_by_side_in_one_window(tmp_path: Path) -> None:
    g = ViewGeometry.from_carm(np.linspace(0, 2 * np.pi, 30, endpoint=False), 0.0, 785.0, 1200.0, bench_detector(40))
    truth = g.transformed(np.eye(3), (3.0, 0.0, 0.0))
    path = tmp_path / "s.h5"
    write_sphere_scan(path, g, truth=truth)
    args = [
        "reconstruct",
        str(path),
        "--algorithm",
        "fdk",
        "--geometry",
        "truth",
        "--shape",
        "16,24,24",
        "--voxel-mm",
        "4",
        "--compare",
        "nominal",
    ]
    res = CliRunner().invoke(cli, args)
    assert res.exit_code == 0, res.output
    figure = tmp_path / "s_fdk_truth_vs_nominal.png"
    assert f"side by side: {figure}" in res.output and figure.read_bytes()[:4] == b"\x89PNG"
    with ScanFile(path) as sf:
        assert sorted(sf.recon_names()) == ["fdk_truth", "fdk_truth_vs_nominal"]
        assert sf.read_recon("fdk_truth_vs_nominal")[1]["geometry"] == "nominal"
    again = CliRunner().invoke(cli, args)
    assert again.exit_code == 2 and "already has a reconstruction named 'fdk_truth'" in again.output
    assert again.output.startswith("error [conflict]: ") and "--overwrite replaces it" in again.output
    assert CliRunner().invoke(cli, [*args, "--overwrite"]).exit_code == 0
    same = CliRunner().invoke(cli, [*args[:-1], "truth", "--overwrite"])
    assert same.exit_code == 2 and "already reconstructed" in same.output


def test_a_reconstruction_estimated_above_the_limit_is_refused_off_a_terminal_unless_asked(tmp_path: Path) -> None:
    g = ViewGeometry.from_carm(np.linspace(0, 2 * np.pi, 40, endpoint=False), 0.0, 785.0, 1200.0, bench_detector(48))
    path = tmp_path / "s.h5"
    write_sphere_scan(path, g)
    args = [
        "reconstruct",
        str(path),
        "--algorithm",
        "pwls",
        "--geometry",
        "nominal",
        "--shape",
        "24,40,40",
        "--voxel-mm",
        "3",
        "--iterations",
        "20",
        "--max-minutes",
        "0.0005",
    ]
    refused = CliRunner().invoke(cli, args)
    assert refused.exit_code == 2 and refused.output.startswith("error [invalid_parameters]: "), refused.output
    assert "is estimated to take" in refused.output and "more than the limit of 0 s" in refused.output
    assert "--yes starts it anyway" in refused.output and "Traceback" not in refused.output
    with ScanFile(path) as sf:
        assert sf.recon_names() == []  # nothing started, nothing stored
    started = CliRunner().invoke(cli, [*args, "--yes"])
    assert started.exit_code == 0, started.output
    assert "(estimated " in started.output
    assert CliRunner(env={"ORBITCT_MAX_MINUTES": "60"}).invoke(cli, [*args[:-2], "--name", "env"]).exit_code == 0


def test_the_time_estimate_follows_the_work() -> None:
    from orbitct.geometry import VolumeGrid
    from recon import reconstruction_seconds

    small, big = VolumeGrid.centered((32, 32, 32), 2.0), VolumeGrid.centered((64, 64, 64), 2.0)
    fdk_s = reconstruction_seconds("fdk", small, 100, 64, 64)
    assert 0 < fdk_s < reconstruction_seconds("fdk", big, 100, 64, 64)
    assert reconstruction_seconds("pwls", small, 100, 64, 64, 10) < reconstruction_seconds(
        "pwls", small, 100, 64, 64, 50
    )


def test_a_failed_calibrated_geometry_is_refused_until_accepted_and_the_volume_says_so(tmp_path: Path) -> None:
    import h5py

    g = ViewGeometry.from_carm(np.linspace(0, 2 * np.pi, 40, endpoint=False), 0.0, 785.0, 1200.0, bench_detector(48))
    path = tmp_path / "s.h5"
    write_sphere_scan(path, g)
    with h5py.File(path, "r+") as f:  # what a calibration that failed its check leaves in the file
        f.copy("geometry/nominal", "geometry/calibrated")
        f["geometry/calibrated"].attrs.update(
            {"quality": "failed", "quality_reasons_json": '["5 of 40 view(s) failed"]', "verdict": "failed"}
        )
    args = ["reconstruct", str(path), "--shape", "16,24,24", "--voxel-mm", "4"]
    refused = CliRunner().invoke(cli, args)
    assert refused.exit_code == 3 and refused.output.startswith("error [failed_quality_check]: "), refused.output
    assert "failed its quality check (5 of 40 view(s) failed)" in refused.output
    assert "--accept-failed-geometry" in refused.output and "Traceback" not in refused.output
    accepted = CliRunner().invoke(cli, [*args, "--accept-failed-geometry"])
    assert accepted.exit_code == 0, accepted.output
    assert "verdict: passed with warnings" in accepted.output and "by explicit override" in accepted.output
    nominal = CliRunner().invoke(cli, [*args, "--geometry", "nominal"])
    assert nominal.exit_code == 0 and "verdict: passed" in nominal.output, nominal.output


def test_the_gpu_says_its_kernels_compile_in_every_run(tmp_path: Path, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """On a GPU (here numba's CUDA simulator) the compile line does not promise a cache the GPU's kernels lack."""
    import recon.pipeline
    from tests.helpers.compiling import compiling_first

    t = np.linspace(0, 2 * np.pi, 8, endpoint=False)
    scan = tmp_path / "tiny.h5"
    write_sphere_scan(scan, ViewGeometry.from_carm(t, 0.0, 785.0, 1200.0, bench_detector(12)))
    # compiling for longer than the half second the command mentions (24 small functions took 0.48 s warm)
    monkeypatch.setattr(recon.pipeline, "fdk", compiling_first(recon.pipeline.fdk, seconds=1.0))
    words = [str(scan), "--geometry", "nominal", "--shape", "6,8,8", "--voxel-mm", "20", "--device", "cuda"]
    r = CliRunner().invoke(cli, ["reconstruct", *words])
    assert r.exit_code == 0, r.output
    assert "device: CUDA simulator (numba, on the CPU), " in r.output and "MiB peak GPU memory" in r.output
    assert "compiling numerical kernels (the GPU's are compiled in every run, the CPU's once after installation" in (
        r.output
    )
    assert "cached for the next run" not in r.output
