"""Metric scale: off by the orbit's mean error along the beam without a scale bar, right with one."""

from __future__ import annotations

import re
from pathlib import Path

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

import calib
from calib.scale import ScaleBarError, find_scale_bar, rescaled_views
from orbitct.scanfile import ScanFile
from tests.helpers.calib_scans import perturbed, sawtooth, spiral_markers, write_scan

MARKERS = spiral_markers(8)
BAR = (0, 7)  # the one pair of these BBs whose distance (114.4 mm) is 9.5 % away from every other pair's
RADIAL_MM = 10.0  # every view 10 mm further from the object than planned: the nominal triangulation is 1.3 % small


def _size_error_pct(xyz: np.ndarray, true_xyz: np.ndarray) -> float:
    """RMS distance from the centroid, calibrated against true (no correspondence needed)."""
    a, b = xyz - xyz.mean(0), true_xyz - true_xyz.mean(0)
    return float(100.0 * (np.sqrt((a**2).sum() / (b**2).sum()) - 1.0))


@pytest.fixture(scope="module")
def far_scan(tmp_path_factory: pytest.TempPathFactory) -> Path:
    nominal = sawtooth(120, 192)
    moved = perturbed(nominal, shift_mm=2.0)
    vec = moved.vectors.copy()
    radial = vec[:, 0:3] / np.linalg.norm(vec[:, 0:3], axis=1, keepdims=True) * RADIAL_MM
    vec[:, 0:3] += radial
    vec[:, 3:6] += radial
    return write_scan(tmp_path_factory.mktemp("scale") / "far.h5", nominal, moved.with_vectors(vec), MARKERS)


def test_rescaled_views_move_no_pixel_of_a_scaled_point() -> None:
    views = perturbed(sawtooth(30, 128))
    points = spiral_markers(6)
    before = views.project(points)
    after = rescaled_views(views, 1.05).project(1.05 * points)
    assert np.allclose(before, after, atol=1e-9)
    assert np.allclose(
        np.linalg.norm(rescaled_views(views, 1.05).S - rescaled_views(views, 1.05).D, axis=1),
        np.linalg.norm(views.S - views.D, axis=1),
    )  # the source-detector assembly is unchanged


def test_the_bar_is_the_one_pair_near_its_length_or_an_error_that_names_the_pairs() -> None:
    d = float(np.linalg.norm(MARKERS[BAR[0]] - MARKERS[BAR[1]]))
    bar = find_scale_bar(MARKERS * 0.99, d)
    assert bar.bbs == BAR and bar.factor == pytest.approx(1 / 0.99)
    with pytest.raises(ScaleBarError, match=r"7 pairs of BBs are within 3 % .*--scale-bar-bbs"):
        find_scale_bar(MARKERS, 72.6)
    with pytest.raises(ScaleBarError, match=r"no pair of BBs is within 3 % of it \(.*at .* mm"):
        find_scale_bar(MARKERS, 30.0)
    assert find_scale_bar(MARKERS, 72.6, bbs=(2, 3)).bbs == (1, 2)
    with pytest.raises(ScaleBarError, match="two different BB numbers from 1 to 8"):
        find_scale_bar(MARKERS, 72.6, bbs=(3, 9))


@pytest.mark.slow
def test_a_scale_bar_fixes_the_scale_the_nominal_geometry_gets_wrong(far_scan: Path, tmp_path: Path) -> None:
    plain = calib.calibrate_scan(far_scan, out=tmp_path / "plain.h5")
    assert abs(_size_error_pct(plain.xyz, MARKERS)) > 0.8  # the gauge took the nominal triangulation's size
    assert "scale bar fixes it" in plain.scale_line()
    length = float(np.linalg.norm(MARKERS[BAR[0]] - MARKERS[BAR[1]]))
    anchored = calib.calibrate_scan(far_scan, out=tmp_path / "bar.h5", scale_bar_mm=length)
    assert abs(_size_error_pct(anchored.xyz, MARKERS)) <= 0.2
    assert anchored.quality is not None and anchored.quality.passed
    # the same pixels: the rescaled frame reprojects exactly as well
    assert anchored.reproj_rms_px == pytest.approx(plain.reproj_rms_px, rel=1e-6)
    assert anchored.scale_bar is not None
    with h5py.File(tmp_path / "bar.h5") as f:
        attrs = f["geometry/calibrated"].attrs
        assert "scale bar" in str(attrs["gauge"]) and attrs["scale_factor"] == pytest.approx(anchored.scale_bar.factor)
        assert np.allclose(f["markers/xyz"][()], anchored.xyz)
    with ScanFile(tmp_path / "bar.h5") as sf:  # the stored geometry reprojects the stored BBs where they were seen
        proj = sf.projection_indices
        seen = np.isfinite(anchored.uv[proj, :, 0])
        err = np.linalg.norm(sf.geometry("calibrated")[proj].project(anchored.xyz) - anchored.uv[proj], axis=-1)[seen]
        assert np.sqrt(np.mean(err**2)) == pytest.approx(anchored.reproj_rms_px, rel=1e-3)


@pytest.mark.slow
def test_cli_takes_the_bar_and_names_a_pair_it_cannot_find(far_scan: Path, tmp_path: Path) -> None:
    from orbitct_app.cli.main import cli

    runner = CliRunner()
    out = tmp_path / "cli.h5"
    ok = runner.invoke(cli, ["calibrate", str(far_scan), "--out", str(out), "--scale-bar-mm", "114.4"])
    assert ok.exit_code == 0, ok.output
    found = re.search(r"metric scale from a 114.4 mm scale bar: BBs (\d+) and (\d+) were ([\d.]+) mm apart", ok.output)
    assert found is not None, ok.output
    named = runner.invoke(
        cli,
        [
            "calibrate",
            str(far_scan),
            "--out",
            str(tmp_path / "named.h5"),
            "--scale-bar-mm",
            "114.4",
            "--scale-bar-bbs",
            f"{found[1]},{found[2]}",
        ],
    )
    assert named.exit_code == 0 and f"BBs {found[1]} and {found[2]} were {found[3]} mm apart" in named.output
    bad = runner.invoke(cli, ["calibrate", str(far_scan), "--out", str(tmp_path / "bad.h5"), "--scale-bar-mm", "72.6"])
    assert bad.exit_code == 1 and "pairs of BBs are within 3 %" in bad.output and "Traceback" not in bad.output
    usage = runner.invoke(cli, ["calibrate", str(far_scan), "--scale-bar-mm", "50", "--scale-bar-bbs", "1-8"])
    assert usage.exit_code == 2 and "--scale-bar-bbs': expected I,J: integers separated by commas" in usage.output
    three = runner.invoke(cli, ["calibrate", str(far_scan), "--scale-bar-mm", "50", "--scale-bar-bbs", "1,2,3"])
    assert three.exit_code == 2 and "--scale-bar-bbs: List should have at most 2 items" in three.output, three.output
    alone = runner.invoke(cli, ["calibrate", str(far_scan), "--scale-bar-bbs", "1,2"])
    assert alone.exit_code == 2 and "give its length too (scale_bar_mm)" in alone.output, alone.output
