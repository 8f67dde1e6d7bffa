"""reconstruct_scan end to end on small scan files: storage, exports, geometry choice, clear errors."""

from __future__ import annotations

import shutil
import time
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest
import tifffile

from orbitct.geometry import ViewGeometry
from orbitct.scanfile import ScanFile, ScanFileError
from recon import (
    BadFramesError,
    FieldOfViewError,
    GeometryMissingError,
    MemoryBudgetError,
    ReconError,
    ReconExistsError,
    VolumeGrid,
    reconstruct_scan,
    rmse,
)
from recon.quality import fov_mask
from tests.helpers.recon import bench_detector, voxelized_spheres, write_sphere_scan

SHAPE = (40, 64, 64)
VOXEL = 2.0


def _sawtooth(n: int = 60, size: int = 72) -> ViewGeometry:
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return ViewGeometry.from_carm(t, np.radians(20) * np.sin(2 * t), 785.0, 1200.0, bench_detector(size))


def _perturbed(g: ViewGeometry, seed: int = 5) -> ViewGeometry:
    """The views the bench really took: smooth angle errors and isocenter shifts, as in the paper's profiles."""
    n = g.n_views
    s = np.linspace(0, 1, n)
    rng = np.random.default_rng(seed)
    ang = np.stack([np.radians(1.5) * np.sin(2 * np.pi * (k + 1) * s + rng.uniform(0, 6)) for k in range(3)], 1)
    shift = np.stack([2.5 * np.sin(2 * np.pi * (k + 2) * s + rng.uniform(0, 6)) for k in range(3)], 1)
    from orbitct.rotations import rotvec_to_matrix

    return g.transformed(rotvec_to_matrix(ang), shift)


@pytest.fixture(scope="module")
def scan_a(tmp_path_factory: pytest.TempPathFactory) -> Path:
    nominal = _sawtooth()
    path = tmp_path_factory.mktemp("recon") / "a.h5"
    write_sphere_scan(path, nominal, truth=_perturbed(nominal))
    return path


@pytest.mark.slow
def test_true_geometry_pwls_beats_fdk_and_nominal_is_worse(scan_a: Path, tmp_path: Path) -> None:
    grid = VolumeGrid.centered(SHAPE, VOXEL)
    truth = voxelized_spheres(grid)
    mask = fov_mask(grid, 70.0, 24.0)
    out = {}
    for alg, geo in (("fdk", "truth"), ("pwls", "truth"), ("pwls", "nominal")):
        res = reconstruct_scan(scan_a, algorithm=alg, geometry=geo, voxel_mm=VOXEL, shape=SHAPE, iterations=15)
        assert res.grid == grid
        out[(alg, geo)] = rmse(res.volume, truth, mask)
    assert out[("pwls", "truth")] < out[("fdk", "truth")]
    assert out[("pwls", "nominal")] > 1.5 * out[("pwls", "truth")]
    with ScanFile(scan_a) as sf:
        assert sf.recon_names() == ["fdk_truth", "pwls_nominal", "pwls_truth"]
        vol, attrs = sf.read_recon("pwls_truth")
        assert vol.shape == SHAPE and attrs["algorithm"] == "pwls" and attrs["geometry"] == "truth"
        assert np.allclose(attrs["voxel_mm"], VOXEL) and attrs["iterations"] == 15


def test_exports_and_progress(scan_a: Path, tmp_path: Path) -> None:
    events = []
    res = reconstruct_scan(
        scan_a,
        algorithm="fdk",
        geometry="nominal",
        voxel_mm=VOXEL,
        shape=SHAPE,
        name="quick",
        export=["nifti", "tiff", "png"],
        out_dir=tmp_path,
        progress=events.append,
    )
    names = sorted(p.name for p in res.exported)
    assert names == [
        "a_quick.nii.gz",
        "a_quick.tif",
        "a_quick_axial.png",
        "a_quick_coronal.png",
        "a_quick_sagittal.png",
    ]
    img = nib.load(str(tmp_path / "a_quick.nii.gz"))
    assert img.shape == SHAPE[::-1]
    assert np.allclose(img.affine[:3, 3], res.origin_mm)
    assert np.allclose(np.asarray(img.dataobj)[:, :, 20].T, res.volume[20])
    assert tifffile.imread(tmp_path / "a_quick.tif").shape == SHAPE
    assert any(e.stage == "fdk" and e.done == e.total for e in events)


def test_clear_errors(scan_a: Path) -> None:
    with pytest.raises(GeometryMissingError, match="no calibrated geometry.*calibrate"):
        reconstruct_scan(scan_a, geometry="calibrated")
    with pytest.raises(ReconError, match="algorithm: Input should be 'fdk' or 'pwls'"):
        reconstruct_scan(scan_a, algorithm="art", geometry="nominal")
    with pytest.raises(ReconError, match=r"shape.0: Input should be less than or equal to 2048"):  # the options' limit
        reconstruct_scan(scan_a, geometry="nominal", voxel_mm=0.05, shape=(3000, 3000, 3000), name="too_big")
    huge = VolumeGrid((3000, 3000, 3000), 0.05, (-75.0, -75.0, -75.0))  # a grid given whole: memory is checked
    with pytest.raises(MemoryBudgetError, match="GiB"):
        reconstruct_scan(scan_a, geometry="nominal", grid=huge, name="too_big")
    with ScanFile(scan_a, "r+") as sf:
        g = sf.geometry("nominal")[sf.projection_indices]
    far = g.transformed(np.eye(3), (600.0, 0.0, 0.0))
    path = scan_a.with_name("far.h5")
    write_sphere_scan(path, far)
    with pytest.raises(FieldOfViewError, match="misses the field of view"):
        reconstruct_scan(path, algorithm="fdk", geometry="nominal", voxel_mm=VOXEL, shape=SHAPE)


def test_pwls_streaming_from_the_scan_file_matches_in_memory(scan_a: Path) -> None:
    """stream='file' re-reads projections and weights chunk by chunk; the volume equals the in-memory run."""
    kw = dict(algorithm="pwls", geometry="truth", voxel_mm=3.0, shape=(24, 40, 40), iterations=3)
    mem = reconstruct_scan(scan_a, stream="memory", name="mem", **kw)
    fil = reconstruct_scan(scan_a, stream="file", name="file", **kw)
    assert mem.params["stream"] == "memory" and fil.params["stream"] == "file"
    np.testing.assert_allclose(fil.volume, mem.volume, rtol=1e-4, atol=1e-5 * float(mem.volume.max()))
    np.testing.assert_allclose(fil.cost, mem.cost, rtol=1e-4)
    with ScanFile(scan_a) as sf:
        stored, attrs = sf.read_recon("file")
        np.testing.assert_array_equal(stored, fil.volume)
    with pytest.raises(ReconError, match="stream: Input should be 'auto', 'memory' or 'file'"):
        reconstruct_scan(scan_a, stream="disk", **kw)
    with pytest.raises(ReconError, match="metal artifact reduction needs"):
        reconstruct_scan(scan_a, stream="file", mar=True, **kw)


def test_memory_estimate_of_streamed_pwls_is_three_volumes() -> None:
    from recon.pipeline import choose_stream, estimate_bytes

    grid = VolumeGrid.centered((128, 128, 128), 1.0)
    vol, proj = grid.nbytes, 4 * 180 * 128 * 128
    streamed = estimate_bytes("pwls", grid, 180, 128, 128, False, "file")
    in_memory = estimate_bytes("pwls", grid, 180, 128, 128, False, "memory")
    assert 3 * vol < streamed < 1.1 * 1.5 * (vol + proj)  # the estimate carries a 10 % margin
    assert in_memory > streamed + 2 * proj
    assert choose_stream("auto", "pwls", grid, 180, 128, 128, False) == "memory"  # 20 MiB fits anywhere
    assert choose_stream("auto", "pwls", grid, 10**7, 2048, 2048, False) == "file"
    assert choose_stream("file", "fdk", grid, 180, 128, 128, False) == "memory"


def test_an_existing_reconstruction_is_replaced_only_when_asked(scan_a: Path, tmp_path: Path) -> None:
    path = tmp_path / "copy.h5"
    path.write_bytes(scan_a.read_bytes())
    kw = dict(algorithm="fdk", geometry="nominal", voxel_mm=VOXEL, shape=SHAPE, name="mine")
    first = reconstruct_scan(path, **kw)
    with pytest.raises(ReconExistsError, match="already has a reconstruction named 'mine'"):
        reconstruct_scan(path, **{**kw, "shape": (8, 8, 8)})
    with ScanFile(path) as sf:
        assert sf.read_recon("mine")[0].shape == first.volume_shape  # untouched
    assert reconstruct_scan(path, **{**kw, "shape": (8, 8, 8)}, overwrite=True).volume_shape == (8, 8, 8)


@pytest.mark.parametrize(
    "damage,why",
    [
        (lambda a: np.full_like(a, np.nan), "pixels NaN or infinite"),
        (lambda a: np.where(np.arange(a.size).reshape(a.shape) % 7 == 0, np.inf, a), "pixels NaN or infinite"),
        (lambda a: np.zeros_like(a), "all zero"),
        (lambda a: np.full_like(a, 65535), "saturated"),
    ],
)
def test_unusable_frames_are_named_and_no_volume_is_stored(tmp_path: Path, damage, why: str) -> None:  # type: ignore[no-untyped-def]
    import h5py

    path = tmp_path / "bad.h5"
    write_sphere_scan(path, _sawtooth(24, 32))
    with h5py.File(path, "r+") as f:
        data = f["frames/data"][:].astype(np.float32)
        del f["frames/data"]
        data[9] = damage(data[9])
        f.create_dataset("frames/data", data=data if "NaN" in why else np.clip(data, 0, 65535).astype(np.uint16))
    with pytest.raises(BadFramesError, match=rf"1 of the 28 frames needed are unusable: frame 9 \(.*{why}"):
        reconstruct_scan(path, algorithm="fdk", geometry="nominal", voxel_mm=4.0, shape=(8, 16, 16))
    with ScanFile(path) as sf:
        assert sf.recon_names() == []


def test_no_results_go_into_a_file_still_acquiring(scan_a: Path, tmp_path: Path) -> None:
    import h5py

    path = tmp_path / "live.h5"
    path.write_bytes(scan_a.read_bytes())
    with h5py.File(path, "r+") as f:
        f.attrs["status"] = "acquiring"
    with pytest.raises(ScanFileError, match="still marked 'acquiring'.*orbitct scan repair"):
        reconstruct_scan(path, algorithm="fdk", geometry="nominal", voxel_mm=VOXEL, shape=(8, 8, 8))


def test_the_default_grid_is_fitted_to_the_object_and_says_so(tmp_path: Path) -> None:
    from orbitct.geometry import ViewGeometry
    from tests.helpers.recon import bench_detector, voxelized_spheres, write_sphere_scan

    # a 60 mm ball (and two inside it) in a field of view about 280 mm across
    g = ViewGeometry.from_carm(np.linspace(0, 2 * np.pi, 60, endpoint=False), 0.0, 785.0, 1200.0, bench_detector(96))
    path = tmp_path / "ball.h5"
    write_sphere_scan(path, g)
    fov = reconstruct_scan(path, algorithm="fdk", geometry="nominal", fit="fov", name="fov")
    obj = reconstruct_scan(path, algorithm="fdk", geometry="nominal", name="obj")
    assert "fitted to the object" in obj.params["grid_choice"] and "whole field of view" in fov.params["grid_choice"]
    assert np.prod(obj.volume_shape) < 0.25 * np.prod(fov.volume_shape)
    ext = obj.grid.extent_mm
    assert (ext[:, 0] <= -60.0).all() and (ext[:, 1] >= 60.0).all()  # the whole ball, with its margin
    assert (ext[:, 0] >= -60.0 - 25.0).all() and (ext[:, 1] <= 60.0 + 25.0).all()  # and not much more
    truth = voxelized_spheres(obj.grid)
    err = lambda v: float(np.sqrt(np.mean((v - truth) ** 2)))  # noqa: E731
    on_fov = fov.volume[
        tuple(
            slice(int(round((obj.grid.origin_mm[a] - fov.grid.origin_mm[a]) / fov.voxel_mm[a])), None)
            for a in (2, 1, 0)
        )
    ][: obj.volume_shape[0], : obj.volume_shape[1], : obj.volume_shape[2]]
    assert on_fov.shape == obj.volume.shape
    assert err(obj.volume) < 1.05 * err(on_fov)  # the same image where the object is


@pytest.mark.parametrize("experiment", ["A", "C"])
def test_the_fitted_grid_holds_all_of_the_phantom(tmp_path: Path, experiment: str) -> None:
    from orbitct.phantoms import experiment_phantom
    from orbitct.simulator.scan import simulate_scan
    from recon import reference_volume

    path = tmp_path / f"{experiment}.h5"
    simulate_scan(experiment, out=path, n_frames=60, detector_px=128)
    obj = reconstruct_scan(path, algorithm="fdk", geometry="truth", name="obj")
    fov = reconstruct_scan(path, algorithm="fdk", geometry="truth", name="fov", fit="fov")
    phantom = reference_volume(experiment_phantom(experiment, 0), fov.grid, supersample=1)
    z, y, x = fov.grid.coords_mm()
    ext = obj.grid.extent_mm
    inside = (
        ((x >= ext[0, 0]) & (x <= ext[0, 1]))[None, None, :]
        & ((y >= ext[1, 0]) & (y <= ext[1, 1]))[None, :, None]
        & ((z >= ext[2, 0]) & (z <= ext[2, 1]))[:, None, None]
    )
    assert phantom[~inside].sum() <= 1e-3 * phantom.sum()  # nothing of the object (BBs included) left outside
    assert obj.volume.size < fov.volume.size


def test_kernels_compiled_on_first_use_are_timed_apart(
    scan_a: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The first reconstruction after installation compiles kernels: said apart, not counted in its time."""
    import recon.pipeline
    from tests.helpers.compiling import compiling_first

    monkeypatch.setattr(recon.pipeline, "fdk", compiling_first(recon.pipeline.fdk))
    scan = tmp_path / "a.h5"
    shutil.copyfile(scan_a, scan)
    t = time.perf_counter()
    res = reconstruct_scan(scan, algorithm="fdk", geometry="truth", shape=[16, 24, 24], name="c", overwrite=True)
    wall = time.perf_counter() - t
    assert res.compile_s > 0.0 and res.params["compile_s"] == res.compile_s, "the test compiled nothing"
    assert 0.0 < res.elapsed_s <= wall - res.compile_s + 1e-6
