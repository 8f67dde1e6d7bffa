"""The CUDA backend under numba's CUDA simulator (tests/conftest.py turns it on): every kernel on tiny problems against
the CPU kernels, the exact adjoint, FDK, PWLS and MAR through the pipeline, and the ``device`` option and its errors."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from orbitct.geometry import Panel, ViewGeometry
from recon import ReconError, VolumeGrid, reconstruct_scan
from recon.cuda import CudaBackprojector, CudaProjector, CudaViewsData, peak_bytes, reset_peak
from recon.device import gpu_problem, make_projector, resolve_device, simulated
from recon.fdk import FdkWeights, fdk, ramp_filter
from recon.operator import Projector, backproject_voxels
from recon.pwls import ViewsData, pwls_sps
from recon.pwls_setup import PwlsResult
from tests.helpers.recon import bench_detector, write_sphere_scan


@pytest.fixture
def tiny_geometry() -> ViewGeometry:
    """Five perturbed, tilted views on a 6 x 7 panel."""
    rng = np.random.default_rng(7)
    n = 5
    return ViewGeometry.from_carm(
        rng.uniform(0, 2 * np.pi, n),
        rng.uniform(-0.7, 0.7, n),
        rng.uniform(250, 320, n),
        520.0,
        Panel(6, 7, 6.0, 5.0),
        du=rng.normal(0, 4, n),
        dv=rng.normal(0, 4, n),
        eta=rng.normal(0, 0.3, n),
        shift=rng.normal(0, 3, (n, 3)),
    )


TINY_GRID = VolumeGrid.centered((5, 6, 7), (6.0, 5.5, 6.5), (1.0, -2.0, 0.5))


def test_the_simulator_stands_in_for_the_gpu_and_auto_still_picks_the_cpu() -> None:
    assert simulated()
    assert gpu_problem() is None
    assert resolve_device("cuda") == "cuda"
    assert resolve_device("auto") == "cpu"
    assert resolve_device("cpu") == "cpu"
    with pytest.raises(ReconError, match="device must be one of auto, cpu, cuda"):
        resolve_device("gpu")
    assert isinstance(make_projector(TINY_GRID, _line(), "cuda"), CudaProjector)


def _line() -> ViewGeometry:
    return ViewGeometry.from_carm(np.array([0.0]), np.array([0.0]), 300.0, 520.0, Panel(4, 4, 8.0, 8.0))


@pytest.mark.parametrize("chunk_views", [1, 2, 5])
def test_forward_and_adjoint_equal_the_cpu_kernels(tiny_geometry: ViewGeometry, chunk_views: int) -> None:
    rng = np.random.default_rng(chunk_views)
    cpu = Projector(TINY_GRID, tiny_geometry)
    gpu = CudaProjector(TINY_GRID, tiny_geometry, chunk_bytes=chunk_views * 4 * 6 * 7)
    assert gpu.chunk_views == chunk_views
    x = rng.random(TINY_GRID.shape).astype(np.float32)
    y = rng.random(cpu.proj_shape).astype(np.float32)
    fx = gpu(x)
    np.testing.assert_allclose(fx, cpu(x), rtol=2e-6, atol=2e-6 * float(fx.max()))
    bt = gpu.T(y)
    np.testing.assert_allclose(bt, cpu.T(y), rtol=1e-5, atol=1e-5 * float(bt.max()))
    assert fx.max() > 0 and bt.max() > 0


@pytest.mark.parametrize("seed", [0, 1])
def test_the_cuda_adjoint_is_exact(tiny_geometry: ViewGeometry, seed: int) -> None:
    rng = np.random.default_rng(seed)
    A = CudaProjector(TINY_GRID, tiny_geometry)
    x = rng.random(TINY_GRID.shape).astype(np.float32)
    y = rng.random(A.proj_shape).astype(np.float32)
    lhs = float(np.dot(A(x).ravel().astype(np.float64), y.ravel()))
    rhs = float(np.dot(x.ravel().astype(np.float64), A.T(y).ravel()))
    assert lhs > 0
    assert abs(lhs - rhs) / lhs < 1e-6


def test_views_of_a_chunk_and_padded_volumes_go_where_the_cpu_puts_them(tiny_geometry: ViewGeometry) -> None:
    rng = np.random.default_rng(3)
    cpu = Projector(TINY_GRID, tiny_geometry)
    gpu = CudaProjector(TINY_GRID, tiny_geometry, chunk_bytes=2 * 4 * 6 * 7)
    xp = np.zeros(cpu.padded_shape, np.float32)
    xp[1:-1, 1:-1, 1:-1] = rng.random(TINY_GRID.shape)
    a = gpu.forward_padded(xp, np.empty((3, 6, 7), np.float32), start=1)
    np.testing.assert_allclose(a, cpu.forward_padded(xp, np.empty((3, 6, 7), np.float32), start=1), rtol=2e-6)
    y = rng.random((3, 6, 7)).astype(np.float32)
    acc_g = np.ones(cpu.padded_shape, np.float32)
    acc_c = np.ones(cpu.padded_shape, np.float32)
    gpu.back_padded(y, acc_g, start=2)
    cpu.back_padded(y, acc_c, start=2)
    np.testing.assert_allclose(acc_g[1:-1, 1:-1, 1:-1], acc_c[1:-1, 1:-1, 1:-1], rtol=1e-5)
    with pytest.raises(ReconError, match="outside"):
        gpu.forward_padded(xp, np.empty((3, 6, 7), np.float32), start=4)
    assert isinstance(gpu.subset(np.array([0, 2])), CudaProjector)


def test_the_fdk_back_projector_equals_the_cpu_one(tiny_geometry: ViewGeometry) -> None:
    rng = np.random.default_rng(4)
    y = rng.random((5, 6, 7)).astype(np.float32)
    w = rng.uniform(0.5, 2.0, 5)
    cpu = backproject_voxels(y, TINY_GRID, tiny_geometry, w)
    padded = np.zeros((5, 8, 9), np.float32)
    padded[:, 1:-1, 1:-1] = y
    reset_peak()
    bp = CudaBackprojector(TINY_GRID)
    bp.add(padded[:3], tiny_geometry[:3], w[:3])
    bp.add(padded[3:], tiny_geometry[3:], w[3:])
    gpu = bp.read(np.empty(TINY_GRID.shape, np.float32))
    assert cpu.max() > 0 and np.count_nonzero(cpu) > cpu.size // 4
    np.testing.assert_allclose(gpu, cpu, rtol=1e-5, atol=1e-6 * float(cpu.max()))
    assert peak_bytes() >= 4 * cpu.size
    with pytest.raises(ReconError, match="padded views"):
        bp.add(y, tiny_geometry, w)


def _small_circle() -> tuple[ViewGeometry, VolumeGrid]:
    t = np.linspace(0, 2 * np.pi, 8, endpoint=False)
    return ViewGeometry.from_carm(t, np.radians(15) * np.sin(2 * t), 785.0, 1200.0, bench_detector(10)), (
        VolumeGrid.centered((6, 8, 8), 20.0)
    )


def test_fdk_on_the_device_equals_fdk_on_the_cpu() -> None:
    g, grid = _small_circle()
    y = Projector(grid, g)(np.random.default_rng(5).random(grid.shape).astype(np.float32))
    cpu = fdk(y, grid, g, chunk=3)
    gpu = fdk(y, grid, g, chunk=3, device="cuda")
    np.testing.assert_allclose(gpu, cpu, rtol=1e-4, atol=1e-5 * float(np.abs(cpu).max()))


def test_a_short_scan_is_filtered_with_parker_weights_on_the_device() -> None:
    t = np.linspace(0, np.pi + 0.9, 9)
    g = ViewGeometry.from_carm(t, np.zeros(9), 785.0, 1200.0, Panel(9, 11, 30.0, 30.0))
    grid = VolumeGrid.centered((5, 8, 8), 20.0)
    weights = FdkWeights.of(g, "hann")
    assert weights.parker is not None
    y = Projector(grid, g)(np.random.default_rng(9).random(grid.shape).astype(np.float32))
    cpu = fdk(y, grid, g, window="hann")
    gpu = fdk(y, grid, g, window="hann", device="cuda")
    np.testing.assert_allclose(gpu, cpu, rtol=1e-4, atol=1e-5 * float(np.abs(cpu).max()))


def test_the_ramp_taps_convolve_as_the_fft_filters() -> None:
    """The GPU's direct convolution with the circular impulse response equals the zero-padded FFT filtering."""
    H = ramp_filter(13, "shepp-logan")
    taps = FdkWeights(H, np.ones(1), None).taps
    row = np.random.default_rng(10).random(13)
    npad = taps.size
    direct = [sum(row[j] * taps[(c - j) % npad] for j in range(13)) for c in range(13)]
    fft = np.fft.irfft(np.fft.rfft(row, npad) * H, npad)[:13]
    np.testing.assert_allclose(direct, fft, rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize(("subsets", "momentum", "weighted"), [(1, False, True), (2, True, True), (3, False, False)])
def test_pwls_on_the_device_follows_the_cpu_iterates(subsets: int, momentum: bool, weighted: bool) -> None:
    g, grid = _small_circle()
    rng = np.random.default_rng(6)
    truth = rng.random(grid.shape).astype(np.float32)
    y = Projector(grid, g)(truth) + rng.normal(0, 0.01, (8, 10, 10)).astype(np.float32)
    w = rng.uniform(0.5, 1.0, y.shape).astype(np.float32) if weighted else None
    kw = {"iterations": 3, "subsets": subsets, "momentum": momentum, "beta": 0.05, "final_cost": True}
    kept: dict[str, np.ndarray] = {}
    seen: dict[str, list[np.ndarray]] = {"cpu": [], "cuda": []}

    def run(A: Projector) -> PwlsResult:
        return pwls_sps(
            A,
            y,
            w,
            keep_data_curvature=lambda c: kept.__setitem__(A.device, c.copy()),
            callback=lambda _, image: seen[A.device].append(image.copy()),
            **kw,
        )

    cpu = run(Projector(grid, g))
    gpu = run(CudaProjector(grid, g, chunk_bytes=3 * 400))
    np.testing.assert_allclose(gpu.cost, cpu.cost, rtol=1e-5)
    np.testing.assert_allclose(gpu.volume, cpu.volume, rtol=1e-4, atol=1e-5 * float(cpu.volume.max()))
    assert gpu.beta_abs == pytest.approx(cpu.beta_abs, rel=1e-6) and gpu.restarts == cpu.restarts
    np.testing.assert_allclose(kept["cuda"], kept["cpu"], rtol=1e-5, atol=1e-7)
    assert len(seen["cuda"]) == len(seen["cpu"]) == 3
    np.testing.assert_allclose(seen["cuda"][0], seen["cpu"][0], rtol=1e-4, atol=1e-5 * float(cpu.volume.max()))


def test_the_data_term_keeps_its_data_on_the_device_or_streams_it() -> None:
    g, grid = _small_circle()
    rng = np.random.default_rng(8)
    y = rng.random((8, 10, 10)).astype(np.float32)
    w = rng.random((8, 10, 10)).astype(np.float32)
    xp = np.zeros(tuple(n + 2 for n in grid.shape), np.float32)
    xp[1:-1, 1:-1, 1:-1] = rng.random(grid.shape)
    cpu = ViewsData(Projector(grid, g), y, w, subsets=2)
    want = np.zeros_like(xp)
    value = cpu.gradient(xp, 1, want)
    curv = np.zeros_like(xp)
    cpu.curvature(curv)
    for resident in (2**30, 0):
        data = CudaViewsData(CudaProjector(grid, g, chunk_bytes=400), y, w, subsets=2, resident_bytes=resident)
        got = np.zeros_like(xp)
        assert data.gradient(xp, 1, got) == pytest.approx(value, rel=1e-6)
        np.testing.assert_allclose(got[1:-1, 1:-1, 1:-1], want[1:-1, 1:-1, 1:-1], rtol=1e-5, atol=1e-7)
        c = np.zeros_like(xp)
        data.curvature(c)
        np.testing.assert_allclose(c[1:-1, 1:-1, 1:-1], curv[1:-1, 1:-1, 1:-1], rtol=1e-5, atol=1e-7)
    with pytest.raises(ReconError, match="weights: expected shape"):
        CudaViewsData(CudaProjector(grid, g), y, w[:4])


@pytest.fixture(scope="module")
def tiny_scan(tmp_path_factory: pytest.TempPathFactory) -> Path:
    t = np.linspace(0, 2 * np.pi, 8, endpoint=False)
    g = ViewGeometry.from_carm(t, np.radians(15) * np.sin(2 * t), 785.0, 1200.0, bench_detector(12))
    path = tmp_path_factory.mktemp("cuda") / "tiny.h5"
    write_sphere_scan(path, g)
    return path


@pytest.mark.parametrize(
    "options",
    [
        {"algorithm": "fdk"},
        {"algorithm": "pwls", "iterations": 2, "subsets": 2, "momentum": True},
        {"algorithm": "pwls", "iterations": 2, "mar": True, "metal_mu_per_mm": 0.02},
    ],
    ids=["fdk", "pwls", "pwls-mar"],
)
def test_reconstruct_scan_on_the_device_equals_the_cpu(tiny_scan: Path, options: dict[str, object]) -> None:
    common = {"geometry": "nominal", "shape": [6, 8, 8], "voxel_mm": 20.0, "overwrite": True, **options}
    cpu = reconstruct_scan(tiny_scan, device="cpu", name="on_cpu", **common)
    gpu = reconstruct_scan(tiny_scan, device="cuda", name="on_gpu", **common)
    assert cpu.params["device"].startswith("CPU (")
    assert "device_peak_bytes" not in cpu.params
    assert gpu.params["device"] == "CUDA simulator (numba, on the CPU)"
    assert gpu.params["device_peak_bytes"] >= 4 * 8 * 10 * 10  # at least one padded volume
    assert cpu.volume is not None and gpu.volume is not None
    scale = float(np.abs(cpu.volume).max())
    np.testing.assert_allclose(gpu.volume, cpu.volume, rtol=1e-3, atol=1e-4 * scale)
    if cpu.cost:
        np.testing.assert_allclose(gpu.cost, cpu.cost, rtol=1e-4)
    auto = reconstruct_scan(tiny_scan, name="auto", **common)
    assert auto.params["device"].startswith("CPU (")


def _without_simulator() -> dict[str, str]:
    env = dict(os.environ)
    env.pop("NUMBA_ENABLE_CUDASIM", None)
    return env


def test_asking_for_the_gpu_where_there_is_none_says_so_in_one_line(tiny_scan: Path) -> None:
    """No GPU backend here (CI has no GPU): ``--device cuda`` is refused with one line, ``auto`` runs on the CPU."""
    cli = [sys.executable, "-m", "orbitct_app.cli.main", "reconstruct", str(tiny_scan), "--geometry", "nominal"]
    grid = ["--shape", "6,8,8", "--voxel-mm", "20", "--overwrite"]
    bad = subprocess.run([*cli, *grid, "--device", "cuda"], capture_output=True, text=True, env=_without_simulator())
    assert bad.returncode != 0
    lines = bad.stderr.strip().splitlines()
    assert len(lines) == 1, bad.stderr
    assert "cannot reconstruct on the GPU" in lines[0] and "--device cpu" in lines[0]
    assert "Traceback" not in bad.stderr
    ok = subprocess.run([*cli, *grid, "--device", "auto"], capture_output=True, text=True, env=_without_simulator())
    assert ok.returncode == 0, ok.stderr
    assert "device: CPU (" in ok.stdout
    wrong = subprocess.run([*cli, "--device", "gpu"], capture_output=True, text=True, env=_without_simulator())
    assert wrong.returncode == 2 and "gpu" in wrong.stderr and "Traceback" not in wrong.stderr


def test_the_estimate_measures_the_gpu_when_it_reconstructs_there(monkeypatch: pytest.MonkeyPatch) -> None:
    """``device='cuda'`` estimates from the GPU kernels' own rates (measured here on a probe small enough for the
    simulator; the pipeline estimates from the CPU's under the simulator, whose speed says nothing of a GPU's)."""
    from recon import estimate

    for name, value in (("_PROBE", 8), ("_PROBE_VIEWS", 2), ("_FDK_PROBE_VIEWS", 2)):
        monkeypatch.setattr(estimate, name, value)
    estimate.projector_rates.cache_clear()
    estimate.rates.cache_clear()
    estimate.fdk_rate.cache_clear()
    try:
        forward, back, per_voxel_view = estimate.rates("cuda")
        assert forward > 0 and back > 0 and per_voxel_view > 0
        grid = VolumeGrid.centered((8, 8, 8), 20.0)
        assert estimate.reconstruction_seconds("pwls", grid, 4, 8, 8, 2, device="cuda") > 0
    finally:
        estimate.projector_rates.cache_clear()
        estimate.rates.cache_clear()
        estimate.fdk_rate.cache_clear()


def test_work_that_does_not_fit_on_the_gpu_is_refused_before_it_starts(
    monkeypatch: pytest.MonkeyPatch, tiny_scan: Path
) -> None:
    import recon.cuda

    class SmallGpu:
        def get_memory_info(self) -> tuple[int, int]:
            return 2**20, 2**30  # 1 MiB free of 1 GiB

    monkeypatch.setattr(recon.cuda.cuda, "current_context", SmallGpu)
    with pytest.raises(ReconError, match=r"a 128 x 128 x 128 volume needs 8 MiB of GPU memory and 1 MiB of 1.0 GiB"):
        CudaBackprojector(VolumeGrid.centered((128, 128, 128), 1.0))
    with pytest.raises(ReconError, match="use a larger voxel size or a smaller shape, or --device cpu"):
        reconstruct_scan(tiny_scan, device="cuda", geometry="nominal", shape=[64, 64, 64], voxel_mm=3.0, name="big")


def test_without_the_gpu_extra_nothing_imports_cuda(tiny_scan: Path) -> None:
    """``auto`` on a machine without the extra picks the CPU without importing numba.cuda at all."""
    code = (
        "import sys, recon\n"
        f"r = recon.reconstruct_scan({str(tiny_scan)!r}, geometry='nominal', shape=[6, 8, 8], voxel_mm=20.0, "
        "name='lazy', overwrite=True)\n"
        "print(r.params['device'].split(' ')[0], 'numba.cuda' in sys.modules)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=_without_simulator())
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["CPU", "False"]


def test_a_failing_gpu_is_said_in_one_sentence(monkeypatch: pytest.MonkeyPatch, tiny_scan: Path) -> None:
    import recon.cuda

    class CudaAPIError(Exception):
        pass

    CudaAPIError.__module__ = "numba.cuda.cudadrv.driver"  # what the driver raises, e.g. when memory runs out

    def fail(*args: object, **kwargs: object) -> None:
        raise CudaAPIError("[2] Call to cuMemAlloc results in CUDA_ERROR_OUT_OF_MEMORY\nmore")

    monkeypatch.setattr(recon.cuda.CudaBackprojector, "add_projections", fail)
    with pytest.raises(ReconError) as caught:
        reconstruct_scan(tiny_scan, device="cuda", geometry="nominal", shape=[6, 8, 8], voxel_mm=20.0, name="oom")
    assert str(caught.value) == (
        "the GPU failed ([2] Call to cuMemAlloc results in CUDA_ERROR_OUT_OF_MEMORY); --device cpu reconstructs on "
        "the CPU"
    )
