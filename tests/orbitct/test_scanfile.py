"""Scan files: round trip, crash-readability, and a clear ScanFileError for every malformed case."""

from collections.abc import Callable
from pathlib import Path

import h5py
import numpy as np
import pytest

from orbitct.geometry import Panel, ViewGeometry
from orbitct.scanfile import ScanFile, ScanFileError, ScanWriter, frame_problem

DET = Panel(8, 10, 1.5, 1.25)


def _write(path: Path, n_proj: int = 5, finish: bool = True) -> ViewGeometry:
    th = np.linspace(0, 1, n_proj)
    geom = ViewGeometry.from_carm(th, 0.1, 785.0, 1200.0, DET)
    w = ScanWriter(
        path,
        DET,
        axes={"stage.angle": "deg"},
        orbit_name="circular",
        orbit_params={"n_frames": n_proj},
        config={"sad_mm": 785.0},
        marker_diameter_mm=3.17,
    )
    rng = np.random.default_rng(0)
    w.append(np.full(DET.shape, 100, np.uint16), "dark", 0.0)
    w.append(np.full(DET.shape, 16000, np.uint16), "flat", 0.1)
    for i in range(n_proj):
        w.append(
            rng.integers(1000, 9000, DET.shape),
            "projection",
            0.2 + i,
            nominal_vector=geom.vectors[i],
            encoders={"stage.angle": float(i)},
            commanded={"stage.angle": float(i)},
        )
    w.write_truth(np.concatenate([np.full((2, 12), np.nan), geom.vectors]), np.zeros((3, 3)), {"name": "x"})
    if finish:
        w.finish()
    return geom


def test_round_trip(tmp_path: Path) -> None:
    path = tmp_path / "s.h5"
    geom = _write(path)
    with ScanFile(path) as f:
        assert f.panel == DET and f.n_frames == 7 and f.status == "complete"
        assert f.count_by_kind() == {"projection": 5, "flat": 1, "dark": 1, "invalid": 0}
        assert f.projection_indices.tolist() == [2, 3, 4, 5, 6]
        g = f.geometry("nominal")
        assert not g[:2].valid.any() and g[2:].allclose(geom)
        assert np.allclose(f.h5["geometry/nominal/matrices"][2:], geom.matrices)
        assert f.geometry("truth")[2:].allclose(geom)
        assert f.orbit == ("circular", {"n_frames": 5}) and f.marker_diameter_mm == 3.17
        assert np.allclose(f.axes("encoders")["stage.angle"][2:], np.arange(5))
        assert f.h5["frames/encoders/stage.angle"].attrs["unit"] == "deg"
        dark, flat = f.dark_flat()
        li = f.line_integrals(2)
        raw = f.frames[2].astype(np.float32)
        assert np.allclose(li, -np.log((raw - 100) / (16000 - 100)), rtol=1e-5)
        assert len(list(f.iter_line_integrals())) == 5
        assert f.phantom == {"name": "x"} and f.truth_markers_xyz().shape == (3, 3)


def test_results_written_back(tmp_path: Path) -> None:
    path = tmp_path / "s.h5"
    geom = _write(path)
    with ScanFile(path) as f, pytest.raises(ScanFileError, match="opened read-only"):
        f.set_status("aborted", "x")
    full = ViewGeometry.empty_like(2, DET).concatenate(geom)
    with ScanFile(path, mode="r+") as f:
        f.write_calibration(
            full,
            uv=np.zeros((7, 3, 2)),
            xyz=np.zeros((3, 3)),
            rpe_mm=np.r_[np.nan, np.nan, np.ones(5)],
            method="bb",
            iterations=2,
            elapsed_s=1.0,
            reproj_rms_px=0.1,
        )
        f.write_recon(
            "fdk",
            np.ones((2, 3, 4)),
            voxel_mm=(1, 1, 1),
            origin_mm=(0, 0, 0),
            algorithm="fdk",
            geometry="calibrated",
            iterations=0,
            elapsed_s=0.5,
            params={"filter": "ramp"},
        )
    with ScanFile(path) as f:
        assert f.geometry("calibrated")[2:].allclose(geom)
        assert f.h5["geometry/calibrated"].attrs["rpe_mean_mm"] == 1.0
        vol, attrs = f.read_recon("fdk")
        assert vol.shape == (2, 3, 4) and attrs["algorithm"] == "fdk"


def test_crashed_scan_stays_readable(tmp_path: Path) -> None:
    path = tmp_path / "s.h5"
    _write(path, finish=False)  # writer never finished: status stays 'acquiring'
    with ScanFile(path) as f:
        assert f.status == "acquiring" and f.n_frames == 7


def _mutate(name: str) -> Callable[[h5py.File], None]:
    def fmt(f: h5py.File) -> None:
        f.attrs["format"] = "other.scan"

    def version(f: h5py.File) -> None:
        f.attrs["version"] = 99

    def version_text(f: h5py.File) -> None:
        f.attrs["version"] = "one"

    def no_data(f: h5py.File) -> None:
        del f["frames/data"]

    def no_keys(f: h5py.File) -> None:
        del f["frames/image_key"]

    def no_detector(f: h5py.File) -> None:
        del f["detector"]

    def shape(f: h5py.File) -> None:
        f["detector"].attrs["cols"] = 11

    def lengths(f: h5py.File) -> None:
        f["frames/time_s"].resize(3, axis=0)

    def nan_geometry(f: h5py.File) -> None:
        f["geometry/nominal/vectors"][3, 4] = np.nan

    def nan_truth(f: h5py.File) -> None:
        f["truth/geometry/vectors"][4, 0] = np.nan

    def geometry_shape(f: h5py.File) -> None:
        del f["geometry/nominal/vectors"]
        f["geometry/nominal/vectors"] = np.zeros((7, 9))

    def no_vectors(f: h5py.File) -> None:
        del f["geometry/nominal/vectors"]

    def keys(f: h5py.File) -> None:
        f["frames/image_key"][0] = 7

    def dtype(f: h5py.File) -> None:
        del f["frames/data"]
        f["frames/data"] = np.zeros((7, 8, 10), np.int32)

    def status(f: h5py.File) -> None:
        f.attrs["status"] = "finished"

    def pitch(f: h5py.File) -> None:
        f["detector"].attrs["pitch_mm"] = [1.0, 2.0, 3.0]

    return locals()[name]


@pytest.mark.parametrize(
    "case, message",
    [
        ("fmt", "format tag is 'other.scan', expected 'orbitct.scan'"),
        ("version", "is version 99; this reader supports version 1"),
        ("version_text", "is version 'one'; this reader supports version 1"),
        ("no_data", "missing dataset /frames/data"),
        ("no_keys", "missing dataset /frames/image_key"),
        ("no_detector", "missing group /detector"),
        ("shape", r"/frames/data has shape \(7, 8, 10\), expected \(N, 8, 11\)"),
        ("lengths", "per-frame datasets disagree in length"),
        ("nan_geometry", r"/geometry/nominal/vectors is not finite on projection frames \[3\]"),
        ("nan_truth", r"/truth/geometry/vectors is not finite on projection frames \[4\]"),
        ("geometry_shape", r"/geometry/nominal/vectors has shape \(7, 9\) of float64, expected \(7, 12\)"),
        ("no_vectors", "missing dataset /geometry/nominal/vectors"),
        ("keys", r"/frames/image_key holds \[7\], allowed are 0, 1, 2, 3"),
        ("dtype", "has dtype int32, expected uint16 or float32"),
        ("status", "status is 'finished'"),
        ("pitch", "pitch_mm must hold 2 numbers"),
    ],
)
def test_malformed_files_give_clear_errors(tmp_path: Path, case: str, message: str) -> None:
    path = tmp_path / "bad.h5"
    _write(path)
    with h5py.File(path, "r+") as f:
        _mutate(case)(f)
    with pytest.raises(ScanFileError, match=message) as exc:
        ScanFile(path)
    assert str(path) in str(exc.value)


def test_not_a_scan_file(tmp_path: Path) -> None:
    with pytest.raises(ScanFileError, match="no such file"):
        ScanFile(tmp_path / "missing.h5")
    junk = tmp_path / "junk.h5"
    junk.write_bytes(b"not hdf5 at all")
    with pytest.raises(ScanFileError, match="not a readable HDF5 file"):
        ScanFile(junk)


def test_writer_rejects_bad_input(tmp_path: Path) -> None:
    path = tmp_path / "w.h5"
    w = ScanWriter(path, DET, axes={"stage.angle": "deg"})
    with pytest.raises(ScanFileError, match="does not match detector"):
        w.append(np.zeros((3, 3)), "dark", 0.0)
    with pytest.raises(ScanFileError, match="needs a finite nominal geometry"):
        w.append(np.zeros(DET.shape), "projection", 0.0)
    with pytest.raises(ScanFileError, match="unknown axes"):
        w.append(np.zeros(DET.shape), "dark", 0.0, encoders={"hexapod.X": 1.0})
    w.finish()
    with pytest.raises(ScanFileError, match="already exists"):
        ScanWriter(path, DET)
    with pytest.raises(ScanFileError, match="must look like 'device.axis'"):
        ScanWriter(tmp_path / "x.h5", DET, axes={"angle": "deg"})


def test_summary_names_projections_taken_away_from_their_command(tmp_path: Path) -> None:
    """A sweep that ran ahead of its exposures recorded frames far from their angles while the scan completed
    (a DCArc in continuous mode, before the fix): the summary, and so ``orbitct inspect``, names them."""
    from orbitct.scanfile import scan_summary
    from tests.helpers.scanfiles import write_sweep_ahead_scan

    write_sweep_ahead_scan(tmp_path / "ahead.h5")
    with ScanFile(tmp_path / "ahead.h5") as f:
        off = scan_summary(f)["taken_off_command"]
    assert off == {"stage.angle": {"frames": 2, "max": 9.5, "step": 2.0, "unit": "deg"}}  # a step is 2 deg


@pytest.mark.parametrize(
    ("frame", "problem"),
    [
        (np.zeros((4, 4), np.uint16), "all zero (no signal)"),
        (np.array([[-1.0, 0.0]]), "no pixel above zero (no signal)"),
        (np.array([[np.nan, 1.0]]), "1 pixels NaN or infinite"),
        (np.array([[0, 65535], [65535, 65535]], np.uint16), "saturated (75% of pixels at 65535)"),
        (np.array([[0, 65535]], np.uint16), None),  # half saturated: still usable
        (np.array([[1, 65534]], np.uint16), None),
        (np.array([[-1.0, 2.0]]), None),
    ],
)
def test_a_projection_that_cannot_be_used_says_why(frame: np.ndarray, problem: str | None) -> None:
    assert frame_problem(frame, projection=True) == problem
    assert frame_problem(np.zeros((2, 2), np.uint16), projection=False) is None  # a dark frame may be all zero
