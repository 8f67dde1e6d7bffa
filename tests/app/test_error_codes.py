"""The error catalogue walked: every code the CLI and the API can produce, produced the way a person meets it, reads
as one sentence of what happened and what to do, with the code, its exit or HTTP status, and no class name,
traceback or blank lines."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml
from click.testing import CliRunner
from fastapi.testclient import TestClient

from orbitct_app.cli.main import cli
from orbitct_app.error_codes import CATALOGUE
from orbitct_app.service.safety.latch import StopLatch
from tests.app.service.conftest import Api, _close_all, _open
from tests.helpers.bench import small_config
from tests.helpers.service import SMALL_SAWTOOTH, failed_scan_file, free_port, register_scan
from tests.helpers.smallfs import fill, small_filesystem

pytestmark = [pytest.mark.system, pytest.mark.timeout(300)]
ROOT = Path(__file__).resolve().parents[2]
CLASS_NAME = re.compile(r"\b(?:[A-Z][a-z]+)+(?:Error|Exception|Interrupt)\b|Traceback|<class ")


def _one_sentence(text: str) -> None:
    assert text and "\n" not in text.strip() and not CLASS_NAME.search(text), text
    what, _, advice = text.partition("; ")
    assert len(what) > 8 and len(advice) > 8, f"no what-to-do part: {text}"


def _api_says(r: Any, code: str) -> str:
    body = r.json()
    assert r.status_code == CATALOGUE[code].http_status and body["error"] == code, (code, r.status_code, r.text)
    assert body["advice"] and body["message"].endswith(body["advice"]), body
    _one_sentence(body["message"])
    return str(body["message"])


def _cli_says(output: str, exit_code: int, code: str, exit_status: int | None = None) -> str:
    lines = [line for line in output.splitlines() if line.strip()]
    errors = [line for line in lines if line.startswith("error [")]
    assert len(errors) == 1 and errors[0].startswith(f"error [{code}]: "), (code, output)
    assert exit_code == (CATALOGUE[code].exit_status if exit_status is None else exit_status), (code, exit_code, output)
    assert output.count("\n\n") == 0 and "Traceback" not in output, output
    text = errors[0].split("]: ", 1)[1]
    _one_sentence(text)
    return text


@pytest.fixture
def services(tmp_path: Path) -> Iterator[Any]:
    opened: list[TestClient] = []

    def start(name: str, data: Path | None = None, **overrides: Any) -> Api:
        (tmp_path / name).mkdir(exist_ok=True)
        return _open(
            tmp_path / name,
            data or tmp_path / name / "data",
            opened,
            data_dir=data or tmp_path / name / "data",
            **overrides,
        )

    yield start
    _close_all(opened)


def test_every_error_of_the_api_reads_as_a_sentence_with_its_code(services: Any, tmp_path: Path) -> None:
    api: Api = services("main", pacs_nodes={"down": f"dicom://NOBODY@127.0.0.1:{free_port()}"})
    said: dict[str, str] = {}
    said["invalid_parameters"] = _api_says(
        api.post("/scans", json={**SMALL_SAWTOOTH, "frames": -1}), "invalid_parameters"
    )
    said["bad_request"] = _api_says(
        api.post("/scans", content=b"\xff\xfe{", headers={"Content-Type": "application/json"}),
        "bad_request",
    )
    said["unauthorized"] = _api_says(api.get("/scans", role=None), "unauthorized")
    said["forbidden"] = _api_says(api.post("/scans", role="viewer", json=SMALL_SAWTOOTH), "forbidden")
    said["not_found"] = _api_says(api.get("/scans/0123456789abcdef"), "not_found")
    said["method_not_allowed"] = _api_says(api.request("DELETE", "/scans"), "method_not_allowed")
    said["conflict"] = _api_says(api.post("/stop/reset"), "conflict")
    said["request_too_large"] = _api_says(
        api.post("/scans", content=b" " * (api.service.settings.max_body_bytes + 1)), "request_too_large"
    )
    said["bad_gateway"] = _api_says(api.get("/pacs/down/series"), "bad_gateway")
    scan_id = register_scan(api, failed_scan_file(tmp_path / "failed.h5"))
    body = {"scan_id": scan_id, "algorithm": "fdk", "geometry": "calibrated", "shape": [8, 16, 16]}
    said["failed_quality_check"] = _api_says(
        api.post("/reconstructions", role="analyst", json=body), "failed_quality_check"
    )
    assert "accept_failed_geometry" in said["failed_quality_check"]
    assert api.post("/stop", json={"reason": "catalogue test"}).status_code == 202
    said["stop_latched"] = _api_says(api.post("/scans", json=SMALL_SAWTOOTH), "stop_latched")
    assert "orbitct reset" in said["stop_latched"]
    store, list_scans = api.service.store, api.service.store.list_scans

    def broken(**kwargs: Any) -> Any:
        raise RuntimeError("a fault injected by the test")

    store.list_scans = broken
    try:
        said["internal_error"] = _api_says(api.get("/scans"), "internal_error")
    finally:
        store.list_scans = list_scans
    assert "incident" in said["internal_error"]

    dead = tmp_path / "dead.yaml"  # a bench whose hexapod nobody answers for
    cfg = small_config().model_dump(mode="json")
    cfg["devices"]["hexapod"] = f"tcp://127.0.0.1:{free_port()}"
    dead.write_text(yaml.safe_dump(cfg))
    unplugged = services("unplugged", bench_config=dead, sim=False, dev_token=None)
    said["unavailable"] = _api_says(unplugged.post("/devices/hexapod/reference"), "unavailable")

    with small_filesystem(tmp_path / "disk", 8) as disk:
        first = services("full", disk / "data")
        first.client.__exit__(None, None, None)  # the data directory exists with its database; now the disk fills
        fill(disk, leave_bytes=0)
        full = services("full", disk / "data")
        said["insufficient_storage"] = _api_says(
            full.post("/scans", json={**SMALL_SAWTOOTH, "frames": 4}), "insufficient_storage"
        )

    api_codes = {c for c, k in CATALOGUE.items() if k.http_status is not None}
    assert set(said) == api_codes, api_codes ^ set(said)


def _cli(*args: str) -> Any:
    return CliRunner().invoke(cli, list(args))


def test_every_error_of_the_cli_reads_as_a_sentence_with_its_code(
    services: Any, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    said: dict[str, str] = {}
    r = _cli("scan", "--frames", "x")
    said["invalid_parameters"] = _cli_says(r.output, r.exit_code, "invalid_parameters")
    assert "orbitct scan --help" in said["invalid_parameters"]

    empty = tmp_path / "empty"
    empty.mkdir()
    r = _cli("import", "dicom", str(empty), "--out", str(tmp_path / "x.h5"))
    said["not_found"] = _cli_says(r.output, r.exit_code, "not_found")

    failed = failed_scan_file(tmp_path / "failed.h5")
    r = _cli("reconstruct", str(failed), "--shape", "8,16,16", "--voxel-mm", "4")
    said["failed_quality_check"] = _cli_says(r.output, r.exit_code, "failed_quality_check")
    assert "--accept-failed-geometry" in said["failed_quality_check"]
    r = _cli("reconstruct", str(failed), "--geometry", "nominal", "--shape", "8,16,16", "--voxel-mm", "4")
    assert r.exit_code == 0, r.output
    r = _cli("reconstruct", str(failed), "--geometry", "nominal", "--shape", "8,16,16", "--voxel-mm", "4")
    said["conflict"] = _cli_says(r.output, r.exit_code, "conflict")

    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    r = _cli("simulate", "-e", "A", "--frames", "10", "--detector-size", "32", "--out", str(blocker / "x.h5"))
    said["file_error"] = _cli_says(r.output, r.exit_code, "file_error")

    junk = tmp_path / "junk"
    junk.mkdir()
    (junk / "x.dcm").write_bytes(b"not DICOM at all")
    r = _cli("import", "dicom", str(junk), "--out", str(tmp_path / "junk.h5"))
    said["action_failed"] = _cli_says(r.output, r.exit_code, "action_failed")

    r = _cli("pacs", "find", "--on", f"dicom://NOBODY@127.0.0.1:{free_port()}")
    said["bad_gateway"] = _cli_says(r.output, r.exit_code, "bad_gateway")

    r = _cli("reset", "--url", f"http://127.0.0.1:{free_port()}", "--token", "oct_x")
    said["unavailable"] = _cli_says(r.output, r.exit_code, "unavailable")

    config = tmp_path / "bench.yaml"
    config.write_text(yaml.safe_dump(small_config().model_dump(mode="json")))
    latched = tmp_path / "latched"
    latched.mkdir()
    latch = StopLatch(latched)
    latch.latch("tester", "catalogue test", "cli")
    assert latch.record()
    r = _cli("scan", "--config", str(config), "--sim", "--out", str(tmp_path / "s.h5"), "--data-dir", str(latched))
    said["stop_latched"] = _cli_says(r.output, r.exit_code, "stop_latched")

    api: Api = services("service")  # the remote commands relay the service's refusals with its codes

    def post(url: str, token: str, body: dict[str, Any] | None = None) -> Any:
        path = "/" + url.split("/", 3)[3]
        return api.client.post(path, json=body or {}, headers={"Authorization": f"Bearer {token}"})

    monkeypatch.setattr("orbitct_app.cli.remote._post", post)
    r = _cli("reset", "--url", "http://testserver", "--token", "oct_unknown")
    said["unauthorized"] = _cli_says(r.output, r.exit_code, "unauthorized")
    r = _cli("reset", "--url", "http://testserver", "--token", api.tokens["viewer"])
    said["forbidden"] = _cli_says(r.output, r.exit_code, "forbidden")

    with small_filesystem(tmp_path / "disk", 8) as disk:
        r = _cli(
            "scan",
            "--config",
            str(config),
            "--orbit",
            "circular",
            "--frames",
            "2000",
            "--sim",
            "--out",
            str(disk / "s.h5"),
        )
        said["insufficient_storage"] = _cli_says(r.output, r.exit_code, "insufficient_storage", exit_status=2)

    def broken() -> Any:
        raise RuntimeError("a fault injected by the test")

    monkeypatch.setattr("orbitct.orbits.describe_kinds", broken)
    r = _cli("orbit", "list")
    said["internal_error"] = _cli_says(r.output, r.exit_code, "internal_error")

    said["interrupted"] = _interrupted_scan(config, tmp_path / "interrupted.h5")

    cli_codes = {c for c, k in CATALOGUE.items() if k.exit_status is not None}
    assert set(said) == cli_codes, cli_codes ^ set(said)


def _interrupted_scan(config: Path, out: Path) -> str:
    """``orbitct scan`` on the in-process twins, Ctrl-C once it is writing frames."""
    cmd = [sys.executable, "-m", "orbitct_app.cli.main", "scan", "--config", str(config), "--sim"]
    cmd += ["--orbit", "circular", "--frames", "2000", "--out", str(out)]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    t0 = time.monotonic()
    while not out.exists() and time.monotonic() - t0 < 90:
        assert proc.poll() is None, proc.communicate()
        time.sleep(0.2)
    time.sleep(1.0)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    return _cli_says(err, proc.returncode, "interrupted")
