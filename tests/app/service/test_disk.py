"""The service on a data directory whose disk really fills up (a tmpfs the test mounts): the scan stops cleanly and
is reported, requests get 507 with a plain message instead of 500, /health says so, and once space is freed the
service carries on without a restart."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from tests.helpers.service import (
    SMALL_SAWTOOTH,
    ended,
    free_port,
    parse_sse,
    small_bench_config,
    wait_for,
)
from tests.helpers.smallfs import fill, small_filesystem

pytestmark = [pytest.mark.system, pytest.mark.timeout(240)]
MB = 1 << 20


def _config(folder: Path, reserve_mb: float) -> Path:
    folder.mkdir(exist_ok=True)
    path = small_bench_config(folder, size=256)  # 128 kB per frame
    cfg = yaml.safe_load(path.read_text())
    cfg["storage"] = {"reserve_mb": reserve_mb}
    path.write_text(yaml.safe_dump(cfg))
    return path


def test_the_service_rides_out_a_full_disk(make_api, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    with small_filesystem(tmp_path / "disk", 48) as disk:
        api = make_api(data_dir=disk / "data", bench_config=_config(tmp_path / "config", 4.0))
        assert api.get("/health", role=None).json()["disk"] == "ok"
        r = api.post("/scans", json={**SMALL_SAWTOOTH, "frames": 20})
        complete_id = r.json()["id"]
        assert wait_for(api, f"/scans/{complete_id}", ended, timeout_s=90)["state"] == "complete"
        r = api.post("/scans", json={**SMALL_SAWTOOTH, "frames": 150})
        assert r.status_code == 202, r.text
        scan_id = r.json()["id"]
        wait_for(api, f"/scans/{scan_id}", lambda s: (s.get("frames_done") or 0) >= 10 or ended(s), timeout_s=90)
        filler = fill(disk, leave_bytes=int(1.5 * MB))  # another program fills the disk mid-scan

        scan = wait_for(api, f"/scans/{scan_id}", ended, timeout_s=90)
        assert scan["state"] == "aborted" and "disk nearly full" in scan["reason"], scan
        assert "error" not in scan["summary"] and scan["summary"]["n_frames"] >= 10, scan["summary"]
        events = parse_sse(api.get(f"/scans/{scan_id}/events").text)  # the stream ends
        assert events[-1]["event"] == "end" and events[-1]["data"]["state"] == "aborted"
        health = api.get("/health", role=None).json()
        assert health["disk"] == "full" and health["status"] == "degraded"

        refused = api.post("/scans", json={**SMALL_SAWTOOTH, "frames": 20})
        assert refused.status_code == 507, refused.text
        assert "not enough disk space" in refused.json()["message"] and api.service.rig.busy is None
        more = fill(disk, leave_bytes=0, name="filler2.bin")  # not a byte left: the database cannot write either
        for method, path, body in [
            ("POST", "/calibrations", {"scan_id": complete_id}),
            ("POST", "/scans", {**SMALL_SAWTOOTH, "frames": 20}),
            ("POST", "/plans/bbs", {"experiment": "A", "frames": 20, "detector_px": 64, "bbs": 4}),
        ]:
            r = api.request(method, path, role="dev", json=body)
            assert r.status_code == 507, (path, r.status_code, r.text)
            assert "disk" in r.json()["message"]
        assert api.get(f"/scans/{scan_id}").status_code == 200  # reading still works

        filler.unlink()
        more.unlink()
        assert api.get("/health", role=None).json()["disk"] == "ok"
        r = api.post("/scans", json={**SMALL_SAWTOOTH, "frames": 20})
        assert r.status_code == 202, r.text
        assert wait_for(api, f"/scans/{r.json()['id']}", ended, timeout_s=90)["state"] == "complete"


def test_the_service_starts_on_a_full_disk_and_says_so(make_api, tmp_path: Path, caplog) -> None:  # type: ignore[no-untyped-def]
    with small_filesystem(tmp_path / "disk", 8) as disk:
        first = make_api(data_dir=disk / "data", bench_config=_config(tmp_path / "config", 4.0))
        first.client.__exit__(None, None, None)  # the data directory exists with its database; now the disk fills
        filler = fill(disk, leave_bytes=0)
        api = make_api(data_dir=disk / "data", bench_config=_config(tmp_path / "config", 4.0))
        health = api.get("/health", role=None).json()
        assert health["disk"] == "full" and health["status"] == "degraded"
        assert any("disk" in r.getMessage() and "full" in r.getMessage() for r in caplog.records)
        assert api.get("/scans").status_code == 200
        assert api.post("/scans", json={**SMALL_SAWTOOTH, "frames": 4}).status_code == 507
        filler.unlink()
        r = api.post("/scans", json={**SMALL_SAWTOOTH, "frames": 4})
        assert r.status_code == 202, r.text
        assert wait_for(api, f"/scans/{r.json()['id']}", ended, timeout_s=90)["state"] == "complete"


def test_serve_on_a_fresh_data_directory_of_a_full_disk_says_so_in_one_line(tmp_path: Path) -> None:
    from click.testing import CliRunner

    from orbitct_app.cli.main import cli

    with small_filesystem(tmp_path / "disk", 4) as disk:
        fill(disk, leave_bytes=0)
        result = CliRunner().invoke(
            cli,
            [
                "serve",
                "--config",
                str(_config(tmp_path / "config", 4.0)),
                "--sim",
                "--data-dir",
                str(disk / "data"),
                "--port",
                str(free_port()),
                "--stop-port",
                "0",
            ],
        )  # port + 1 may be taken (CI: Dask's listeners)
        assert result.exit_code == 1, result.output
        assert "cannot start: the disk of the data directory" in result.output and "is full" in result.output
        assert "Traceback" not in result.output
