"""Geometry for other toolkits: each export, read back through the toolkit's own documented projection formula
(written out here from its documentation, not from orbitct's code), puts the scan's BB truth where orbitct projects
it (within 0.05 px); what a toolkit cannot hold is measured and said; failed and incomplete geometries are refused.

The toolkits are not installed for these tests (ASTRA's and tomosipo's cone-beam projectors, TIGRE, LEAP and diffct
need a GPU or a source build, CIL comes from conda): the formulas are their documented conventions (TIGRE's from its
projector's source, CIL's from its conversion to ASTRA)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import pytest
from click.testing import CliRunner
from numpy.typing import NDArray

from orbitct.geometry import ViewGeometry
from orbitct.scanfile import ScanFile, ScanWriter
from orbitct_app.cli.main import cli
from recon.toolkits import toolkit_geometry
from tests.helpers.calib_scans import perturbed, sawtooth, spiral_markers

WITHIN_PX = 0.05


def _scan(path: Path, truth: ViewGeometry, markers: NDArray[np.float64]) -> Path:
    """A scan file (frames blank: only its geometries matter here) with nominal views and the truth."""
    nominal = sawtooth(truth.n_views, truth.panel.rows)
    with ScanWriter(path, truth.panel) as w:
        w.append(np.zeros(truth.panel.shape), "dark", 0.0)
        w.append(np.full(truth.panel.shape, 1000.0), "flat", 0.0)
        for n in range(truth.n_views):
            w.append(np.full(truth.panel.shape, 500.0), "projection", float(n), nominal_vector=nominal.vectors[n])
        w.write_truth(np.concatenate([np.full((2, 12), np.nan), truth.vectors]), markers)
    return path


@pytest.fixture(scope="module")
def bench_scan(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, ViewGeometry, NDArray[np.float64]]:
    truth = perturbed(sawtooth(24, 64), seed=3)
    markers = spiral_markers(12)
    return _scan(tmp_path_factory.mktemp("toolkits") / "scan.h5", truth, markers), truth, markers


def _export(scan: Path, toolkit: str, out: Path, *extra: str) -> tuple[dict[str, Any], Any]:
    res = CliRunner().invoke(cli, ["export", toolkit, str(scan), "--out", str(out), *extra])
    assert res.exit_code == 0, res.output
    return json.loads(out.read_text()), res


def _plane_hit(
    src: NDArray[np.float64], centre: NDArray[np.float64], normal: NDArray[np.float64], x: NDArray[np.float64]
) -> NDArray[np.float64]:
    t = ((centre - src) @ normal) / ((x - src) @ normal)
    return src + t * (x - src)


def _astra(a: dict[str, Any], x: NDArray[np.float64]) -> NDArray[np.float64]:
    """ASTRA cone_vec: (src, d, u, v); pixel (r, c) at d + (c - (cols-1)/2) u + (r - (rows-1)/2) v."""
    out = []
    for row in np.asarray(a["Vectors"]):
        s, d, u, v = row[:3], row[3:6], row[6:9], row[9:]
        hit = _plane_hit(s, d, np.cross(u, v), x) - d
        c, r = np.linalg.lstsq(np.stack([u, v], 1), hit, rcond=None)[0]
        out.append((c + (a["DetectorColCount"] - 1) / 2, r + (a["DetectorRowCount"] - 1) / 2))
    return np.array(out)


def _tomosipo(a: dict[str, Any], x: NDArray[np.float64]) -> NDArray[np.float64]:
    """tomosipo cone_vec (z, y, x vectors): project_point's intersection, then dot(hit, det_u) / |det_u|^2."""
    rows, cols = a["shape"]
    p = x[::-1]
    out = []
    for s, d, v, u in zip(*(np.asarray(a[k]) for k in ("src_pos", "det_pos", "det_v", "det_u")), strict=True):
        hit = _plane_hit(s, d, np.cross(v, u), p) - d
        out.append((hit @ u / (u @ u) + (cols - 1) / 2, hit @ v / (v @ v) + (rows - 1) / 2))
    return np.array(out)


def _leap(a: dict[str, Any], x: NDArray[np.float64]) -> NDArray[np.float64]:
    """LEAP modular beam: s = <c-y,n>/<x-y,n> <x-y,u> - <c-y,u> (t with v), n = u x v; index = s / pitch + (N-1)/2."""
    out = []
    for y, c, v, u in zip(
        *(np.asarray(a[k]) for k in ("sourcePositions", "moduleCenters", "rowVectors", "colVectors")), strict=True
    ):
        n = np.cross(u, v)
        scale = ((c - y) @ n) / ((x - y) @ n)
        s, t = scale * ((x - y) @ u) - (c - y) @ u, scale * ((x - y) @ v) - (c - y) @ v
        out.append((s / a["pixelWidth"] + (a["numCols"] - 1) / 2, t / a["pixelHeight"] + (a["numRows"] - 1) / 2))
    return np.array(out)


def _diffct(a: dict[str, Any], x: NDArray[np.float64]) -> NDArray[np.float64]:
    """diffct cone kernel: pixel (iu, iv) at det_center + (iu + 1/2 - n_u/2) du u + (iv + 1/2 - n_v/2) dv v."""
    out = []
    for s, d, u, v in zip(
        *(np.asarray(a[k]) for k in ("src_pos", "det_center", "det_u_vec", "det_v_vec")), strict=True
    ):
        hit = _plane_hit(s, d, np.cross(u, v), x) - d
        pu, pv = np.linalg.lstsq(np.stack([u * a["du"], v * a["dv"]], 1), hit, rcond=None)[0]
        out.append((pu - 0.5 + a["det_u"] / 2, pv - 0.5 + a["det_v"] / 2))  # (col, row): det_u runs along columns
    return np.array(out)


def _tigre(a: dict[str, Any], x: NDArray[np.float64]) -> NDArray[np.float64]:
    """TIGRE (computeDeltas_Siddon): pixel (0,0) and its two neighbours at x = 0, y = dU (iu - nU/2 + 1/2),
    z = dV (nV/2 - 1/2 - iv), turned by roll/pitch/yaw, moved to x = -(DSD - DSO) and by the detector offsets, turned
    by the ZYZ angles with the source at (DSO, 0, 0), less the image offset; Python arrays hold (z, y, x), (V, U) and
    (yaw, pitch, roll)."""
    n_v, n_u = a["nDetector"]
    d_v, d_u = a["dDetector"]
    out = []
    for i, (alpha, theta, psi) in enumerate(a["angles"]):
        yaw, pitch, roll = a["rotDetector"][i]
        off_v, off_u = a["offDetector"][i]
        oz, oy, ox = a["offOrigin"][i]
        dso, dsd = a["DSO"][i], a["DSD"][i]
        cr, sr, cp, sp, cy, sy = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch), np.cos(yaw), np.sin(yaw)
        rpy = np.array(
            [
                [cr * cp, cr * sp * sy - sr * cy, cr * sp * cy + sr * sy],
                [sr * cp, sr * sp * sy + cr * cy, sr * sp * cy - cr * sy],
                [-sp, cp * sy, cp * cy],
            ]
        )
        ca, sa, ct, st, cs, ss = np.cos(alpha), np.sin(alpha), np.cos(theta), np.sin(theta), np.cos(psi), np.sin(psi)
        zyz = np.array(
            [
                [ca * ct * cs - sa * ss, -ca * ct * ss - sa * cs, ca * st],
                [sa * ct * cs + ca * ss, -sa * ct * ss + ca * cs, sa * st],
                [-st * cs, st * ss, ct],
            ]
        )
        corners = []
        for iu, iv in ((0, 0), (1, 0), (0, 1)):
            p = rpy @ np.array([0.0, d_u * (iu - n_u / 2 + 0.5), d_v * (n_v / 2 - 0.5 - iv)])
            p += np.array([-(dsd - dso), off_u, off_v])
            corners.append(zyz @ p - np.array([ox, oy, oz]))
        src = zyz @ np.array([dso, 0.0, 0.0]) - np.array([ox, oy, oz])
        p0, step_u, step_v = corners[0], corners[1] - corners[0], corners[2] - corners[0]
        hit = _plane_hit(src, p0, np.cross(step_u, step_v), x) - p0
        out.append(np.linalg.lstsq(np.stack([step_u, step_v], 1), hit, rcond=None)[0])  # (iu, iv) = (col, row)
    return np.array(out)


def _cil(a: dict[str, Any], x: NDArray[np.float64]) -> NDArray[np.float64]:
    """CIL Cone3D_Flex through CIL's own conversion to ASTRA (convert_flex_geometry_to_astra_vec_3D): u = +/- the x
    direction times pixel_size[0] (- when the origin is on the right), v = +/- the y direction times pixel_size[1] (-
    when the origin is at the top), ASTRA's rows num_pixels[1] and columns num_pixels[0]."""
    sign_h = -1.0 if "right" in a["origin"] else 1.0
    sign_v = -1.0 if "top" in a["origin"] else 1.0
    vectors = [
        np.concatenate(
            [s, d, sign_h * np.asarray(dx) * a["pixel_size"][0], sign_v * np.asarray(dy) * a["pixel_size"][1]]
        )
        for s, d, dx, dy in zip(
            a["source_position_set"],
            a["detector_position_set"],
            a["detector_direction_x_set"],
            a["detector_direction_y_set"],
            strict=True,
        )
    ]
    cols, rows = a["num_pixels"]
    return _astra({"Vectors": vectors, "DetectorRowCount": rows, "DetectorColCount": cols}, x)


FORMULAS = {"astra": _astra, "tomosipo": _tomosipo, "leap": _leap, "diffct": _diffct, "tigre": _tigre, "cil": _cil}


@pytest.mark.parametrize("toolkit", FORMULAS)
def test_each_export_puts_the_bb_truth_where_orbitct_projects_it(
    bench_scan: tuple[Path, ViewGeometry, NDArray[np.float64]], tmp_path: Path, toolkit: str
) -> None:
    scan, truth, markers = bench_scan
    document, res = _export(scan, toolkit, tmp_path / f"{toolkit}.json", "--geometry", "truth")
    assert document["toolkit"] == toolkit and document["views"] == truth.n_views and document["units"] == "mm"
    assert document["orbitct"] == {"scan": "scan.h5", "geometry": "truth"} and "(exact)" in res.output
    expected = truth.project(markers)  # (views, markers, 2)
    got = np.stack([FORMULAS[toolkit](document["arguments"], m) for m in markers], axis=1)
    assert np.abs(got - expected).max() < WITHIN_PX, np.abs(got - expected).max()


def test_leap_tigre_and_cil_say_how_far_a_skewed_detector_lands(tmp_path: Path) -> None:
    """LEAP's, TIGRE's and CIL's detector axes are orthogonal: a panel skewed by 10 mrad is exported with its error measured and said."""
    truth = perturbed(sawtooth(12, 64), seed=1)
    vectors = truth.vectors.copy()
    vectors[:, 9:12] += 0.01 * vectors[:, 6:9]
    skewed = truth.with_vectors(vectors)
    markers = spiral_markers(8)
    scan = _scan(tmp_path / "skewed.h5", skewed, markers)
    document, res = _export(scan, "leap", tmp_path / "leap.json", "--geometry", "truth")
    off = np.abs(np.stack([_leap(document["arguments"], m) for m in markers], 1) - skewed.project(markers)).max()
    assert 0.05 < off <= document["approximation_px"] + 1e-9
    assert "warning: LEAP cannot hold this geometry exactly" in res.output
    for toolkit, label in (("tigre", "TIGRE"), ("cil", "CIL")):  # their detector axes are orthogonal too
        document, res = _export(scan, toolkit, tmp_path / f"{toolkit}.json", "--geometry", "truth")
        landed = np.stack([FORMULAS[toolkit](document["arguments"], m) for m in markers], 1)
        off = np.abs(landed - skewed.project(markers)).max()
        assert 0.05 < off <= document["approximation_px"] + 1e-9 and f"warning: {label} cannot hold" in res.output
    diffct, res = _export(scan, "diffct", tmp_path / "diffct.json", "--geometry", "truth")  # diffct holds the skew
    assert diffct["approximation_px"] < 1e-6 and "warning" not in res.output


def test_the_default_is_the_calibrated_geometry_and_a_failed_one_is_refused(
    bench_scan: tuple[Path, ViewGeometry, NDArray[np.float64]], tmp_path: Path
) -> None:
    scan, truth, markers = bench_scan
    copy = tmp_path / "calibrated.h5"
    copy.write_bytes(scan.read_bytes())
    vectors = np.concatenate([np.full((2, 12), np.nan), truth.vectors])
    with ScanFile(copy, "r+") as sf:
        sf.write_calibration(
            ViewGeometry(vectors, truth.panel),
            uv=np.zeros((1, 2)),
            xyz=markers,
            rpe_mm=np.zeros(1),
            method="test",
            iterations=1,
            elapsed_s=0.0,
            reproj_rms_px=0.0,
        )
    document, res = _export(copy, "astra", tmp_path / "a.json")
    assert document["orbitct"]["geometry"] == "calibrated" and "of the calibrated geometry" in res.output
    with h5py.File(copy, "r+") as f:
        f["geometry/calibrated"].attrs["quality"] = "failed"
        f["geometry/calibrated"].attrs["quality_reasons_json"] = '["view 3 predicted 0.9 px"]'
    res = CliRunner().invoke(cli, ["export", "leap", str(copy), "--out", str(tmp_path / "l.json")])
    assert res.exit_code != 0 and "failed its quality check (view 3 predicted 0.9 px)" in res.output
    assert "--accept-failed-geometry" in res.output and "Traceback" not in res.output
    _export(copy, "leap", tmp_path / "l2.json", "--accept-failed-geometry")
    with h5py.File(copy, "r+") as f:
        f["geometry/calibrated/vectors"][5] = np.nan  # a view the calibration could not solve
    res = CliRunner().invoke(
        cli, ["export", "diffct", str(copy), "--out", str(tmp_path / "d.json"), "--accept-failed-geometry"]
    )
    assert res.exit_code != 0 and "1 of 24 views have no geometry" in res.output


def test_rtk_and_an_existing_file(bench_scan: tuple[Path, ViewGeometry, NDArray[np.float64]], tmp_path: Path) -> None:
    scan, truth, _ = bench_scan
    res = CliRunner().invoke(cli, ["export", "rtk", str(scan), "--out", str(tmp_path / "g.xml"), "--geometry", "truth"])
    assert res.exit_code == 0 and "24 views of the truth geometry for RTK" in res.output, res.output
    assert (tmp_path / "g.xml").read_text().count("<Projection>") == truth.n_views
    again = CliRunner().invoke(cli, ["export", "rtk", str(scan), "--out", str(tmp_path / "g.xml")])
    assert again.exit_code != 0 and "exists" in again.output


def test_an_unknown_toolkit_is_named() -> None:
    with pytest.raises(ValueError, match="choose one of astra, tomosipo, leap, diffct, tigre, cil"):
        toolkit_geometry(sawtooth(3, 16), "mystery")  # type: ignore[arg-type]
