"""Jobs and a split reconstruction on a real Dask cluster: ``dask scheduler`` and two ``dask worker`` processes on
loopback, started here as a lab starts them."""

from __future__ import annotations

import os
import shutil
import signal
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from orbitct.geometry import ViewGeometry, VolumeGrid
from tests.app.service.test_jobs import _complete_scan, _wait
from tests.helpers.dask_cluster import DaskCluster
from tests.helpers.recon import bench_detector, write_sphere_scan
from tests.helpers.service import SMALL_SAWTOOTH, ended, parse_sse, wait_for

pytestmark = [pytest.mark.system, pytest.mark.slow, pytest.mark.timeout(400)]


@pytest.fixture
def cluster(tmp_path: Path) -> Iterator[DaskCluster]:
    (tmp_path / "dask").mkdir()
    c = DaskCluster(tmp_path / "dask", n_workers=2)
    try:
        yield c
    finally:
        c.close()


@pytest.fixture
def sphere_scan(tmp_path: Path) -> Path:
    t = np.linspace(0, 2 * np.pi, 48, endpoint=False)
    geometry = ViewGeometry.from_carm(t, np.radians(15) * np.sin(2 * t), 785.0, 1200.0, bench_detector(64))
    path = tmp_path / "spheres.h5"
    write_sphere_scan(path, geometry)
    return path


def test_fdk_split_across_two_workers_equals_one_process(
    cluster: DaskCluster, sphere_scan: Path, tmp_path: Path
) -> None:
    from distributed import get_task_stream

    import recon

    other = tmp_path / "single.h5"
    shutil.copyfile(sphere_scan, other)
    grid = VolumeGrid.centered((32, 48, 48), 2.5)
    client = cluster.client()
    try:
        with get_task_stream(client=client) as stream:
            split = recon.reconstruct_scan(sphere_scan, algorithm="fdk", geometry="nominal", grid=grid, cluster=client)
        single = recon.reconstruct_scan(other, algorithm="fdk", geometry="nominal", grid=grid)
    finally:
        client.close()
    parts = [t for t in stream.data if "orbitct-fdk" in str(t["key"]) and "sum" not in str(t["key"])]
    assert len(parts) == 4 and len({t["worker"] for t in parts}) == 2  # two parts on each of the two workers
    assert split.params["cluster_workers"] == 2
    scale = float(np.abs(single.volume).max())
    np.testing.assert_allclose(split.volume, single.volume, rtol=0, atol=1e-5 * scale)  # float32 round-off


def test_pwls_split_across_two_workers_equals_one_process(
    cluster: DaskCluster, sphere_scan: Path, tmp_path: Path
) -> None:
    from distributed import get_task_stream

    import recon

    other = tmp_path / "single.h5"
    shutil.copyfile(sphere_scan, other)
    grid = VolumeGrid.centered((32, 48, 48), 2.5)
    kwargs = {"algorithm": "pwls", "geometry": "nominal", "grid": grid, "iterations": 4, "subsets": 5, "momentum": True}
    client = cluster.client()
    try:
        with get_task_stream(client=client) as stream:
            split = recon.reconstruct_scan(sphere_scan, cluster=client, **kwargs)
        single = recon.reconstruct_scan(other, **kwargs)
    finally:
        client.close()
    keys = [str(t["key"]) for t in stream.data]
    parts = [t for t in stream.data if "orbitct-pwls" in str(t["key"]) and "part" in str(t["key"])]
    assert len(parts) == 2 and len({t["worker"] for t in parts}) == 2  # one part of the views on each worker
    assert sum("subset" in k and "sum" not in k for k in keys) == 2 * 5 * 4  # 2 parts x 5 subsets x 4 passes
    assert split.params["cluster_workers"] == 2 and split.params["stream"] == "cluster"
    scale = float(np.abs(single.volume).max())
    np.testing.assert_allclose(split.volume, single.volume, rtol=0, atol=1e-4 * scale)  # float32 round-off
    np.testing.assert_allclose(split.cost, single.cost, rtol=1e-5)


def test_workers_reconstruct_their_views_on_their_gpus(cluster: DaskCluster, tmp_path: Path) -> None:
    """``device='cuda'`` on a cluster: each worker projects its views on its GPU (here numba's CUDA simulator, which
    the workers inherit from the test process), and the volume equals one process's on the CPU."""
    import sys

    import recon

    t = np.linspace(0, 2 * np.pi, 8, endpoint=False)
    geometry = ViewGeometry.from_carm(t, np.radians(15) * np.sin(2 * t), 785.0, 1200.0, bench_detector(12))
    scan = tmp_path / "tiny.h5"
    write_sphere_scan(scan, geometry)
    other = tmp_path / "single.h5"
    shutil.copyfile(scan, other)
    common = {"geometry": "nominal", "shape": [6, 8, 8], "voxel_mm": 20.0}
    client = cluster.client()
    try:
        for options in ({"algorithm": "fdk"}, {"algorithm": "pwls", "iterations": 2, "subsets": 2}):
            split = recon.reconstruct_scan(scan, cluster=client, device="cuda", overwrite=True, **common, **options)
            single = recon.reconstruct_scan(other, device="cpu", overwrite=True, **common, **options)
            assert split.params["device"] == "Dask workers (their GPUs)"
            scale = float(np.abs(single.volume).max())
            np.testing.assert_allclose(split.volume, single.volume, rtol=0, atol=1e-4 * scale)
        on_gpu = client.run(lambda: "recon.cuda" in sys.modules)
    finally:
        client.close()
    assert len(on_gpu) == 2 and all(on_gpu.values())


def _hold_the_gpu(seconds: float) -> tuple[float, float, list[str]]:
    """On a worker: hold this machine's GPU as a reconstruction job does; when it was held, and what was said."""
    from orbitct_app.service.jobs.tasks import one_job_per_gpu

    said: list[str] = []
    with one_job_per_gpu(lambda event: said.append(event.message)):
        start = time.time()
        time.sleep(seconds)
        return start, time.time(), said


def test_two_reconstruction_jobs_never_share_one_gpu(cluster: DaskCluster) -> None:
    """Two GPU jobs on two workers of one machine take its GPU in turn; the one that waits says so."""
    client = cluster.client()
    try:
        workers = sorted(client.scheduler_info()["workers"])
        assert len(workers) == 2
        futures = [client.submit(_hold_the_gpu, 1.0, pure=False, workers=[w]) for w in workers]
        first, second = client.gather(futures)
    finally:
        client.close()
    (a0, a1, said_a), (b0, b1, said_b) = sorted([first, second])
    assert b0 >= a1 - 0.05  # one after the other
    assert said_b == ["waiting for the GPU: another reconstruction is using it"] and said_a == []


def test_pwls_that_would_not_fit_a_workers_memory_limit_is_refused_before_loading(sphere_scan: Path) -> None:
    import dask
    from distributed import Client, LocalCluster

    import recon
    from recon.cluster import ClusterError

    grid = VolumeGrid.centered((32, 48, 48), 2.5)
    off = {f"distributed.worker.memory.{k}": False for k in ("target", "spill", "pause", "terminate")}
    with (
        dask.config.set(off),
        LocalCluster(
            n_workers=1, threads_per_worker=1, processes=False, memory_limit="1MB", dashboard_address=None
        ) as local,
        Client(local, set_as_default=False) as client,
    ):
        with pytest.raises(ClusterError, match=r"needs about .* GiB on each of 1 worker.*memory limit"):
            recon.reconstruct_scan(
                sphere_scan, algorithm="pwls", geometry="nominal", grid=grid, iterations=1, cluster=client
            )
        assert not client.has_what()[next(iter(client.scheduler_info()["workers"]))]  # nothing was loaded


def test_a_worker_killed_mid_pwls_ends_in_the_same_image_or_a_clear_failure(
    cluster: DaskCluster, sphere_scan: Path, tmp_path: Path
) -> None:
    import threading

    import recon
    from recon.cluster import ClusterError

    other = tmp_path / "single.h5"
    shutil.copyfile(sphere_scan, other)
    grid = VolumeGrid.centered((32, 48, 48), 2.5)
    kwargs = {"algorithm": "pwls", "geometry": "nominal", "grid": grid, "iterations": 40, "subsets": 4}
    client, outcome = cluster.client(), {}

    def run() -> None:
        try:
            outcome["result"] = recon.reconstruct_scan(sphere_scan, cluster=client, **kwargs)
        except ClusterError as exc:
            outcome["error"] = exc

    thread = threading.Thread(target=run)
    thread.start()
    try:
        worker = _worker_running(client, "subset")  # PWLS is under way: the parts hold their views
        pid = client.run(os.getpid, workers=[worker])[worker]
        os.kill(pid, signal.SIGKILL)
        thread.join(timeout=240.0)
        assert not thread.is_alive(), "the reconstruction hangs after a worker was killed"
    finally:
        client.close()
    if "error" in outcome:
        assert "the cluster lost the PWLS of" in str(outcome["error"])
        return
    single = recon.reconstruct_scan(other, **kwargs)  # the lost part was read again elsewhere: the same image
    scale = float(np.abs(single.volume).max())
    np.testing.assert_allclose(outcome["result"].volume, single.volume, rtol=0, atol=1e-4 * scale)


def test_calibration_and_reconstruction_jobs_run_on_the_cluster_with_progress(
    make_api: Any, cluster: DaskCluster
) -> None:
    api = make_api(dask_scheduler=cluster.address)
    r = api.post("/scans", json={**SMALL_SAWTOOTH, "frames": 40})
    assert r.status_code == 202, r.text
    scan_id = r.json()["id"]
    assert wait_for(api, f"/scans/{scan_id}", ended)["state"] == "complete"
    cal = api.post("/calibrations", role="analyst", json={"scan_id": scan_id}).json()["id"]
    rec = api.post(
        "/reconstructions",
        role="analyst",
        json={"scan_id": scan_id, "algorithm": "fdk", "geometry": "calibrated", "shape": [24, 32, 32]},
    ).json()["id"]
    pwls = api.post(
        "/reconstructions",
        role="analyst",
        json={
            "scan_id": scan_id,
            "algorithm": "pwls",
            "geometry": "calibrated",
            "shape": [24, 32, 32],
            "iterations": 2,
            "subsets": 2,
            "momentum": True,
        },
    ).json()["id"]
    workers = set(cluster.client().scheduler_info()["workers"])
    for job_id in (cal, rec, pwls):
        job = _wait(api, job_id, timeout_s=180.0)
        assert job["state"] == "succeeded", job
        events = parse_sse(api.get(f"/jobs/{job_id}/events").text)
        assert sum(e["event"] == "progress" for e in events) >= 3
        log = " ".join(line["line"] for line in api.get(f"/jobs/{job_id}/log").json())
        assert "the Dask scheduler at " + cluster.address in log
        assert any(f"running on the Dask worker {w}" in log for w in workers), log
    recon_job = api.get(f"/jobs/{rec}").json()
    assert recon_job["result"]["shape"] == [24, 32, 32]
    assert recon_job["result"]["workers"] == 2  # the job's FDK split its views across both workers
    pwls_job = api.get(f"/jobs/{pwls}").json()
    assert (
        pwls_job["result"]["workers"] == 2 and len(pwls_job["result"]["cost"]) == 2
    )  # PWLS's views too (2 iterations)


def _worker_running(client: Any, key_part: str, timeout_s: float = 60.0) -> str:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        for worker, keys in client.processing().items():
            if any(key_part in str(k) for k in keys):
                return str(worker)
        time.sleep(0.05)
    raise AssertionError(f"no worker is running {key_part}")


def _slow_job(
    make_api: Any, cluster: DaskCluster, monkeypatch: pytest.MonkeyPatch, frames: int
) -> tuple[Any, str, str]:
    """A service on the cluster running the frame-means workload (0.1 s a frame) on a scan of ``frames`` frames:
    the service, the scan and the job."""
    from orbitct_app.service.jobs import manager as jobs_module
    from tests.helpers.workloads import frame_means

    monkeypatch.setitem(jobs_module.JOB_TARGETS, "calibration", frame_means)
    api = make_api(dask_scheduler=cluster.address)
    scan_id = _complete_scan(api, n=frames)
    return api, scan_id, api.service.jobs.submit("calibration", scan_id, {"delay_s": 0.1}, "t")


def test_a_worker_killed_mid_job_ends_in_a_completed_job_or_a_clear_failure(
    make_api: Any, cluster: DaskCluster, monkeypatch: pytest.MonkeyPatch
) -> None:
    api, _, job_id = _slow_job(make_api, cluster, monkeypatch, 40)
    client = cluster.client()
    try:
        worker = _worker_running(client, job_id)
        pid = client.run(os.getpid, workers=[worker])[worker]
        time.sleep(0.5)
        os.kill(pid, signal.SIGKILL)  # the worker process dies mid-job (its nanny starts a new one)
    finally:
        client.close()
    job = _wait(api, job_id, timeout_s=120.0)
    if job["state"] == "failed":
        assert "worker" in job["reason"] and "died" in job["reason"], job
    else:
        assert job["state"] == "succeeded", job  # Dask ran the (read-only) work again on a live worker
        assert job["result"]["n"] == 42


def test_a_scheduler_that_goes_away_fails_running_jobs_with_the_reason(
    make_api: Any, cluster: DaskCluster, monkeypatch: pytest.MonkeyPatch
) -> None:
    api, scan_id, job_id = _slow_job(make_api, cluster, monkeypatch, 200)
    _wait(api, job_id, ("running",))
    time.sleep(1.0)
    cluster.kill_scheduler()
    t0 = time.monotonic()
    job = _wait(api, job_id, ("failed", "succeeded", "cancelled"), timeout_s=90.0)
    assert job["state"] == "failed" and "Dask scheduler at " + cluster.address in job["reason"], job
    assert "went away" in job["reason"]
    assert time.monotonic() - t0 < 60.0
    assert api.get("/jobs").status_code == 200  # the service keeps answering
    assert api.get(f"/jobs/{job_id}/log").status_code == 200
    assert api.get("/health").json()["jobs"] == "lost"
    later = api.service.jobs.submit("calibration", scan_id, {}, "t")  # waits for the cluster instead of hanging
    time.sleep(1.0)
    assert api.get(f"/jobs/{later}").json()["state"] == "queued"


def test_cli_reconstructs_on_the_cluster_and_refuses_what_it_cannot(cluster: DaskCluster, sphere_scan: Path) -> None:
    from click.testing import CliRunner

    from orbitct_app.cli.main import cli

    base = ["reconstruct", str(sphere_scan), "--geometry", "nominal", "--shape", "24,32,32"]
    r = CliRunner().invoke(cli, [*base, "--algorithm", "fdk", "--scheduler", cluster.address])
    assert r.exit_code == 0, r.output
    assert f"views split across 2 Dask workers at {cluster.address}" in r.output
    r = CliRunner().invoke(cli, [*base, "--algorithm", "pwls", "--iterations", "2", "--scheduler", cluster.address])
    assert r.exit_code == 0, r.output
    assert f"views split across 2 Dask workers at {cluster.address}" in r.output and "cost " in r.output
    r = CliRunner().invoke(cli, [*base, "--algorithm", "pwls", "--mar", "--scheduler", cluster.address])
    assert r.exit_code == 2 and "--mar runs on this machine" in r.output
    r = CliRunner().invoke(cli, [*base, "--algorithm", "fdk", "--scheduler", "localhost:8786"])
    assert r.exit_code == 2 and "tcp://HOST:PORT" in r.output
    r = CliRunner().invoke(cli, [*base, "--algorithm", "fdk", "--overwrite", "--scheduler", "tcp://127.0.0.1:9"])
    assert r.exit_code == 1 and "cannot reach the Dask scheduler at tcp://127.0.0.1:9" in r.output
    assert "Traceback" not in r.output


@pytest.mark.parametrize("whose", ["the job's own worker", "a worker holding views"])
def test_a_worker_killed_mid_pwls_job_ends_the_job_within_a_minute(
    make_api: Any, cluster: DaskCluster, whose: str
) -> None:
    """A PWLS reconstruction job splits its views over both workers; one of them is killed mid-run: the job
    succeeds on the restarted worker or fails with a sentence naming what was lost, within a minute."""
    api = make_api(dask_scheduler=cluster.address)
    scan_id = _complete_scan(api, n=60)
    r = api.post(
        "/reconstructions",
        role="analyst",
        json={
            "scan_id": scan_id,
            "algorithm": "pwls",
            "geometry": "nominal",
            "shape": [32, 48, 48],
            "iterations": 60,
            "subsets": 4,
        },
    )
    assert r.status_code == 202, r.text
    job_id = r.json()["id"]
    client = cluster.client()
    try:
        subset_worker = _worker_running(client, "subset", timeout_s=120.0)  # PWLS under way on the cluster
        job_worker = _worker_running(client, job_id)
        victim = (
            job_worker
            if whose == "the job's own worker"
            else next(w for w in client.scheduler_info()["workers"] if w != job_worker)
        )
        assert subset_worker
        pid = client.run(os.getpid, workers=[victim])[victim]
        os.kill(pid, signal.SIGKILL)
        killed_at = time.monotonic()
    finally:
        client.close()
    said = "running it died" if whose == "the job's own worker" else "those views are read again"
    log = ""
    while said not in log:  # the job says within seconds what died
        assert time.monotonic() - killed_at < 10.0, log
        log = " ".join(line["line"] for line in api.get(f"/jobs/{job_id}/log").json())
        time.sleep(0.2)
    job = _wait(api, job_id, timeout_s=60.0)
    assert time.monotonic() - killed_at < 60.0
    if job["state"] == "failed":
        assert "Traceback" not in job["reason"] and ("worker" in job["reason"] or "lost" in job["reason"]), job
    else:
        assert job["state"] == "succeeded", job
        assert len(job["result"]["cost"]) == 60  # the cost at each of the 60 iterations' starts
