"""Helpers shared by the service tests: a small scan file and SSE parsing."""

from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import h5py
import httpx
import numpy as np
import yaml

from orbitct.geometry import Panel, ViewGeometry
from orbitct.scanfile import ScanWriter
from tests.helpers.recon import bench_detector, write_sphere_scan

ROOT = Path(__file__).resolve().parents[2]
DETECTOR_PX = 192  # the twins keep the detector size of their first start in a process


def write_small_scan(path: Path, n: int = 6, size: int = 16) -> Path:
    """A complete scan file of ``n`` projections of ``size``^2 pixels (plus a dark and a flat)."""
    det = Panel(size, size, 427.0 / size, 427.0 / size)
    theta = np.linspace(0, np.pi, n)
    geom = ViewGeometry.from_carm(theta, np.zeros(n), 785.0, 1200.0, det)
    with ScanWriter(path, det, orbit_name="circular", orbit_params={"n_frames": n}) as w:
        w.append(np.zeros((size, size), np.uint16), "dark", 0.0)
        w.append(np.full((size, size), 1000, np.uint16), "flat", 0.0)
        for i in range(n):
            w.append(np.full((size, size), 100 + i, np.uint16), "projection", 0.1 * i, nominal_vector=geom.vectors[i])
    return path


def parse_sse(text: str) -> list[dict[str, Any]]:
    """Events of a server-sent-event body as dicts with id, event and data."""
    events = []
    for block in text.split("\n\n"):
        fields: dict[str, Any] = {}
        for line in block.splitlines():
            if line.startswith(":") or ":" not in line:
                continue
            key, value = line.split(":", 1)
            fields[key] = value.strip()
        if fields:
            fields["data"] = json.loads(fields.get("data", "null"))
            fields["id"] = int(fields["id"]) if "id" in fields else None  # a stream's opening state has none
            events.append(fields)
    return events


def wait_for(
    api: Any, path: str, done: Callable[[dict[str, Any]], bool], timeout_s: float = 120.0, poll_s: float = 0.05
) -> dict[str, Any]:
    """GET ``path`` until ``done(body)``; the last body."""
    t0 = time.monotonic()
    body: dict[str, Any] = {}
    while time.monotonic() - t0 < timeout_s:
        body = api.get(path).json()
        if done(body):
            return body
        time.sleep(poll_s)
    raise AssertionError(f"{path} not done after {timeout_s} s: {body}")


def ended(body: dict[str, Any]) -> bool:
    """Whether a scan or job has reached a final state."""
    return body.get("state") in ("complete", "aborted", "failed", "interrupted", "succeeded", "cancelled")


SMALL_SAWTOOTH = {"orbit": "sawtooth", "params": {"amplitude_deg": 6.0, "cycles": 2}, "errors": "none"}


def small_bench_config(folder: Path, size: int = DETECTOR_PX) -> Path:
    """The default bench configuration with a small detector and fast frames."""
    cfg = yaml.safe_load((ROOT / "config" / "bench.yaml").read_text())
    cfg["geometry"]["detector"] = {"rows": size, "cols": size}
    cfg["calibration_frames"] = {"darks_before": 2, "flats_before": 2, "darks_after": 1, "flats_after": 1}
    cfg["sim"]["time_scale"] = 50.0
    path = folder / "bench.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


SMALL_CARM_SAWTOOTH = {"orbit": "sawtooth", "params": {"start_deg": -180.0, "amplitude_deg": 10.0}, "errors": "none"}


def small_carm_config(folder: Path, size: int = 64, time_scale: float = 2.0) -> Path:
    """The C-arm configuration with a small panel; its twin moves ``time_scale`` times faster than real."""
    cfg = yaml.safe_load((ROOT / "config" / "carm-zeego.yaml").read_text())
    cfg["geometry"]["detector"] = {"rows": size, "cols": size}
    cfg["calibration_frames"] = {"darks_before": 1, "flats_before": 1, "darks_after": 1, "flats_after": 1}
    cfg["sim"]["time_scale"] = time_scale
    path = folder / "carm.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


def free_port() -> int:
    """A TCP port free on loopback now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def serve_subprocess(
    config: Path, data: Path, dev_token: str, timeout_s: float = 90.0
) -> tuple[subprocess.Popen[bytes], str, dict[str, str]]:
    """``orbitct serve --sim`` in a subprocess, once its rig is connected: the process, base URL and auth header.
    Its log goes to ``<data>-serve.log`` beside the data directory (a pipe nobody reads would stop the service once
    it had logged 64 kB)."""
    port = free_port()
    env = {**os.environ, "ORBITCT_DEV_TOKEN": dev_token, "PYTHONPATH": str(ROOT)}
    log_path = data.parent / f"{data.name}-serve.log"
    data.parent.mkdir(parents=True, exist_ok=True)
    with open(log_path, "ab") as log:
        proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "orbitct_app.cli.main",
                "serve",
                "--config",
                str(config),
                "--sim",
                "--port",
                str(port),
                "--stop-port",
                "0",
                "--data-dir",
                str(data),
                "--log-level",
                "warning",
            ],
            env=env,
            stdout=subprocess.DEVNULL,
            stderr=log,
        )
    base = f"http://127.0.0.1:{port}"
    t0 = time.monotonic()
    while True:
        try:
            if httpx.get(f"{base}/health", timeout=1).json()["bench"] == "connected":
                return proc, base, {"Authorization": f"Bearer {dev_token}"}
        except (httpx.HTTPError, ValueError, KeyError):
            pass
        if proc.poll() is not None or time.monotonic() - t0 > timeout_s:
            proc.kill()
            raise AssertionError("service did not start: " + log_path.read_text(errors="replace")[-2000:])
        time.sleep(0.2)


def failed_scan_file(path: Path) -> Path:
    """A small scan whose calibrated geometry failed its quality check (as a failed calibration leaves it)."""
    g = ViewGeometry.from_carm(np.linspace(0, 2 * np.pi, 40, endpoint=False), 0.0, 785.0, 1200.0, bench_detector(48))
    write_sphere_scan(path, g)
    with h5py.File(path, "r+") as f:
        f.copy("geometry/nominal", "geometry/calibrated")
        f["geometry/calibrated"].attrs.update(
            {"quality": "failed", "quality_reasons_json": '["5 of 40 view(s) failed"]', "verdict": "failed"}
        )
    return path


def register_scan(api: Any, scan_file: Path) -> str:
    """Put ``scan_file`` into the service of ``api`` as a complete scan; its id."""
    from orbitct_app.service.core.files import summarize_scan

    scan_id = "f" * 16
    (api.data_dir / "scans").mkdir(exist_ok=True)
    shutil.copy(scan_file, api.data_dir / "scans" / f"{scan_id}.h5")
    api.service.store.add_scan(
        scan_id, name="failed", orbit="imported", request={}, file=f"scans/{scan_id}.h5", owner="test", frames_total=40
    )
    path = api.data_dir / "scans" / f"{scan_id}.h5"
    api.service.store.update_scan(scan_id, state="complete", frames_done=40, summary=summarize_scan(path))
    return scan_id
