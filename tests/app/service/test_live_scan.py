"""A scan started over the API can calibrate while it runs: BBs on the latest frame, warnings and the running RPE
and predicted error on the scan's event stream, the calibrated geometry in the file when the scan ends, the outcome in its summary."""

from __future__ import annotations

import pytest

from orbitct.scanfile import ScanFile
from tests.helpers.service import SMALL_SAWTOOTH, ended, parse_sse, wait_for

pytestmark = pytest.mark.system


def test_a_live_calibrated_scan_marks_bbs_and_ends_with_the_calibrated_geometry(api) -> None:  # type: ignore[no-untyped-def]
    r = api.post("/scans", json={**SMALL_SAWTOOTH, "frames": 120, "calibrate": "live"})
    assert r.status_code == 202, r.text
    scan_id = r.json()["id"]
    marked = None
    while True:
        scan = api.get(f"/scans/{scan_id}").json()
        if ended(scan):
            break
        frame = api.get(f"/scans/{scan_id}/frames/latest")
        if frame.status_code == 200 and frame.json()["bbs"]:
            marked = frame.json()
    assert scan["state"] == "complete", scan
    assert marked is not None, "the latest frame came with the BBs the live calibration found"
    assert marked["kind"] == "projection" and all(0 <= u < 192 and 0 <= v < 192 for u, v in marked["bbs"])
    live = scan["summary"]["live_calibration"]
    assert live["outcome"] in ("passed",) or live["outcome"].startswith("QUALITY CHECK FAILED"), live
    assert live["bbs"] >= 4 and live["geometry_after_last_frame_s"] > 0
    assert "calibrated" in scan["summary"]["geometries"]
    with ScanFile(api.data_dir / "scans" / f"{scan_id}.h5") as sf:
        assert sf.has_geometry("calibrated")
    events = parse_sse(api.get(f"/scans/{scan_id}/events").text)
    assert {"state", "progress", "calibration", "end"} <= {e["event"] for e in events}
    figures = [e["data"]["metrics"] for e in events if e["event"] == "calibration" and "rpe_mm" in e["data"]["metrics"]]
    assert figures, "the running RPE and predicted error came on the scan's stream while it ran"
    out_of_bounds = [f for f in figures if not (f["bbs"] >= 4 and 0 < f["predicted_px"] < 2.0 and f["rpe_mm"] < 1.0)]
    assert not out_of_bounds, out_of_bounds


def test_live_calibration_options_are_checked_at_the_boundary(api) -> None:  # type: ignore[no-untyped-def]
    r = api.post("/scans", json={**SMALL_SAWTOOTH, "frames": 10, "abort_on": ["bb_lost"]})
    assert r.status_code == 422 and "abort_on needs calibrate: live" in r.text
    r = api.post("/scans", json={**SMALL_SAWTOOTH, "frames": 10, "calibrate": "live", "abort_on": ["nonsense"]})
    assert r.status_code == 422 and "abort_on" in r.text and "bb_lost" in r.text
    r = api.post("/scans", json={**SMALL_SAWTOOTH, "frames": 10, "calibrate": "live", "bb_diameter_mm": -1})
    assert r.status_code == 422 and "bb_diameter_mm" in r.text
    wait_for(api, "/scans", lambda body: all(ended(s) for s in body) if isinstance(body, list) else True)
