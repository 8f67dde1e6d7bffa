"""The CUDA backend on a real GPU at realistic sizes (``make test-gpu``; left out of ``make test``): a simulated
experiment A scan reconstructed by FDK and 5 PWLS iterations on the GPU equals the CPU's within float32 tolerance,
and the adjoint is exact at full panel size. ``ORBITCT_GPU_TEST_PX`` sets the panel (default 384 pixels)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from recon import ReconstructionOptions, reconstruct_scan
from recon.cuda import CudaProjector
from recon.device import describe_device, resolve_device

pytestmark = pytest.mark.gpu

PX = int(os.environ.get("ORBITCT_GPU_TEST_PX", "384"))
FRAMES = max(8, PX // 2)


@pytest.fixture(scope="module")
def scan_a(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from orbitct.simulator import simulate_scan

    path = tmp_path_factory.mktemp("gpu") / "a.h5"
    simulate_scan("A", out=path, n_frames=FRAMES, detector_px=PX, n_dark=2, n_flat=2)
    return path


def test_a_gpu_is_found_and_named() -> None:
    assert resolve_device("auto") == "cuda"
    assert describe_device("cuda").startswith("GPU ")


@pytest.mark.parametrize(
    "options",
    [
        {"algorithm": "fdk"},
        {"algorithm": "pwls", "iterations": 5},
        {"algorithm": "pwls", "iterations": 2, "subsets": 6, "momentum": True, "mar": True},
    ],
    ids=["fdk", "pwls-5", "os-mom-mar"],
)
def test_the_gpu_reconstructs_a_scan_as_the_cpu_does(scan_a: Path, options: dict[str, object]) -> None:
    common = ReconstructionOptions.model_validate(
        {"geometry": "truth", "voxel_mm": min(20.0, 384.0 / PX), "fit": "object", "overwrite": True, **options}
    )
    cpu = reconstruct_scan(scan_a, common, device="cpu", name="cpu")
    gpu = reconstruct_scan(scan_a, common, device="cuda", name="gpu", grid=cpu.grid)
    assert gpu.params["device"] == describe_device("cuda") and gpu.params["device_peak_bytes"] > 0
    assert cpu.volume is not None and gpu.volume is not None
    scale = float(np.percentile(np.abs(cpu.volume), 99.9))
    diff = np.abs(gpu.volume - cpu.volume)
    assert float(diff.max()) < 1e-3 * scale, f"largest difference {diff.max():.3g} against {scale:.3g}"
    if cpu.cost:
        np.testing.assert_allclose(gpu.cost, cpu.cost, rtol=1e-4)


def test_the_adjoint_is_exact_at_full_panel_size(scan_a: Path) -> None:
    from orbitct.scanfile import ScanFile
    from recon import VolumeGrid

    with ScanFile(scan_a) as scan:
        geom = scan.geometry("truth")
    geom = geom[np.flatnonzero(geom.valid)]
    grid = VolumeGrid.centered((PX // 3, PX // 3, PX // 3), 900.0 / PX)
    A = CudaProjector(grid, geom)
    rng = np.random.default_rng(0)
    x = rng.random(grid.shape).astype(np.float32)
    y = rng.random(A.proj_shape).astype(np.float32)
    lhs = float(np.dot(A(x).ravel().astype(np.float64), y.ravel()))
    rhs = float(np.dot(x.ravel().astype(np.float64), A.T(y).ravel()))
    assert abs(lhs - rhs) / lhs < 1e-5
