"""The REST API keeps its OpenAPI contract: schemathesis, every check (all are on unless schemathesis.toml says why
not for one operation), against a real ``orbitct serve --sim`` on
loopback (its examples, the coverage of every schema construct, and random requests): no server error, no status
or body the document does not declare, valid requests accepted, invalid ones refused."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

from tests.helpers.service import SMALL_SAWTOOTH, serve_subprocess, small_bench_config

pytestmark = [pytest.mark.system, pytest.mark.slow, pytest.mark.timeout(900)]
TOKEN = "oct_dev_token_for_the_contract_test_0123"
CONFIG = Path(__file__).with_name("schemathesis.toml")


def _resources(base: str) -> dict[str, str]:
    """A complete scan, and a calibration and a reconstruction of it that have ended: their ids, for the run."""
    with httpx.Client(base_url=base, headers={"Authorization": f"Bearer {TOKEN}"}, timeout=60) as client:
        scan_id = client.post("/scans", json={**SMALL_SAWTOOTH, "frames": 30}).json()["id"]
        while client.get(f"/scans/{scan_id}").json()["state"] in ("queued", "running"):
            time.sleep(0.2)
        cal = client.post("/calibrations", json={"scan_id": scan_id}).json()["id"]
        rec = client.post(
            "/reconstructions", json={"scan_id": scan_id, "geometry": "nominal", "shape": [16, 16, 16]}
        ).json()["id"]
        for job_id in (cal, rec):
            while client.get(f"/jobs/{job_id}").json()["state"] in ("queued", "running"):
                time.sleep(0.2)
    return {
        "ORBITCT_CONTRACT_SCAN": scan_id,
        "ORBITCT_CONTRACT_CALIBRATION": cal,
        "ORBITCT_CONTRACT_RECONSTRUCTION": rec,
    }


def test_the_api_keeps_its_openapi_contract(tmp_path: Path) -> None:
    proc, base, _ = serve_subprocess(small_bench_config(tmp_path), tmp_path / "data", TOKEN)
    report = tmp_path / "schemathesis.json"
    try:
        env = {**os.environ, "ORBITCT_CONTRACT_TOKEN": TOKEN, **_resources(base)}
        run = subprocess.run(
            [
                str(Path(sys.executable).with_name("schemathesis")),
                "--config-file",
                str(CONFIG),
                "run",
                f"{base}/openapi.json",
                "--phases",
                "examples,coverage,fuzzing",
                "--max-examples",
                "15",
                "--workers",
                "1",
                "--seed",
                "1",
                "--report",
                "json",
                "--report-json-path",
                str(report),
                "--no-color",
                "--output-truncate",
                "false",
            ],
            capture_output=True,
            text=True,
            timeout=840,
            env=env,
        )
    finally:
        proc.terminate()
        proc.wait(60)
    summary = json.loads(report.read_text())
    assert run.returncode == 0 and not summary["failures"] and not summary["errors"], run.stdout[-12000:]
    assert summary["operations"]["selected"] >= 50
