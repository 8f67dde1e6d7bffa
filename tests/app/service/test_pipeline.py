"""Through the API on the twins: a scan, its calibration and its reconstruction, with results and events."""

from __future__ import annotations

import io
import threading
import zipfile
from pathlib import Path

import nibabel as nib
import numpy as np
import pydicom
import pytest

from orbitct.scanfile import ScanFile
from tests.helpers.service import SMALL_SAWTOOTH, ended, parse_sse, wait_for

pytestmark = pytest.mark.system


@pytest.mark.slow
def test_scan_calibrate_reconstruct(api, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    r = api.post("/scans", json={**SMALL_SAWTOOTH, "frames": 40, "name": "pipeline"})
    assert r.status_code == 202, r.text
    scan_id = r.json()["id"]
    assert r.headers["location"] == f"/scans/{scan_id}"
    live: dict[str, str] = {}
    reader = threading.Thread(target=lambda: live.update(text=api.get(f"/scans/{scan_id}/events").text))
    reader.start()
    scan = wait_for(api, f"/scans/{scan_id}", ended)
    reader.join(30)
    assert scan["state"] == "complete", scan
    assert scan["summary"]["frames_by_kind"]["projection"] == 40
    assert set(scan["summary"]["geometries"]) >= {"nominal", "truth"}

    events = parse_sse(live["text"])
    assert [e["id"] for e in events] == list(range(1, len(events) + 1))
    done = [
        e["data"]["done"]
        for e in events
        if e["event"] == "progress" and e["data"]["stage"] == "scan" and e["data"]["message"] != "complete"
    ]
    assert done == sorted(done) and done[-1] == scan["frames_total"]
    assert any("rate_fps" in e["data"]["metrics"] for e in events if e["event"] == "progress")
    said = [e["data"] for e in events if e["event"] == "progress" and e["data"]["stage"] == "duration"]
    assert len(said) == 1 and said[0]["metrics"]["expected_s"] > 0  # how long the frames take, said once
    scan = api.get(f"/scans/{scan_id}").json()
    assert scan["progress"]["expected_s"] == said[0]["metrics"]["expected_s"]
    assert events[-1]["event"] == "end" and events[-1]["data"]["state"] == "complete"

    r = api.get(f"/scans/{scan_id}/file")
    assert r.status_code == 200
    (tmp_path / "copy.h5").write_bytes(r.content)
    with ScanFile(tmp_path / "copy.h5") as sf:
        assert sf.status == "complete" and sf.count_by_kind()["projection"] == 40

    # recon on calibrated geometry before any calibration: 409
    assert api.post("/reconstructions", role="analyst", json={"scan_id": scan_id}).status_code == 409

    r = api.post(
        "/calibrations", role="analyst", json={"scan_id": scan_id, "scale_bar_mm": 50.0, "scale_bar_bbs": [0, 2]}
    )
    assert r.status_code == 422 and "scale_bar_bbs" in r.text  # BBs are numbered from 1
    r = api.post("/calibrations", role="analyst", json={"scan_id": scan_id, "method": "bundle"})
    assert r.status_code == 202, r.text
    cal_id = r.json()["id"]
    r = api.post(
        "/reconstructions",
        role="analyst",
        json={"scan_id": scan_id, "algorithm": "fdk", "geometry": "calibrated", "shape": [24, 32, 32]},
    )
    assert r.status_code == 202, r.text  # queued behind the calibration of the same scan
    rec_id = r.json()["id"]

    cal = wait_for(api, f"/jobs/{cal_id}", ended, 300)
    assert cal["state"] == "succeeded", cal
    quality = api.get(f"/calibrations/{cal_id}").json()["result"]["quality"]
    assert isinstance(quality["passed"], bool) and sum(quality["views"].values()) == 40
    assert quality["predicted_px_max"] is not None and quality["centroid_noise_px"] > 0
    assert "metric scale from the nominal geometry" in api.get(f"/calibrations/{cal_id}").json()["result"]["scale"]
    rpe = api.get(f"/calibrations/{cal_id}/rpe").json()
    assert rpe["table"]["frames"] == 40 and rpe["table"]["bbs"] >= 3
    assert rpe["table"]["rpe_mean_mm"] < 1.0 and len(rpe["per_frame_mm"]) == 40
    assert rpe["iterations"][0]["index"] == 0
    files = api.get(f"/calibrations/{cal_id}/files").json()
    png = next(f for f in files if f.endswith(".png"))
    r = api.get(f"/calibrations/{cal_id}/files/{png}")
    assert r.status_code == 200 and r.content[:4] == b"\x89PNG"
    cal_events = parse_sse(api.get(f"/jobs/{cal_id}/events").text)
    stages = [e["data"]["stage"] for e in cal_events if e["event"] == "progress"]
    assert stages and stages[-1] == "write"
    said = [e["data"] for e in cal_events if e["event"] == "progress" and e["data"]["stage"] == "duration"]
    assert len(said) == 1 and said[0]["message"].startswith("calibration takes about ")
    assert cal["progress"]["stage"] == "write" and cal["progress"]["expected_s"] == said[0]["metrics"]["expected_s"]

    rec = wait_for(api, f"/jobs/{rec_id}", ended, 300)
    assert rec["state"] == "succeeded", rec
    assert rec["result"]["shape"] == [24, 32, 32]
    assert rec["progress"]["expected_s"] > 0  # said before it started, kept on the job's record
    r = api.get(f"/reconstructions/{rec_id}/slices/axial")
    assert r.status_code == 200 and r.content[:4] == b"\x89PNG"
    assert api.get(f"/reconstructions/{rec_id}/slices/axial", params={"index": 99}).status_code == 404  # no such slice
    r = api.get(f"/reconstructions/{rec_id}/volume", params={"format": "npy"})
    assert np.load(io.BytesIO(r.content)).shape == (24, 32, 32)
    r = api.get(f"/reconstructions/{rec_id}/volume")
    assert r.status_code == 200 and r.content[:2] == b"\x1f\x8b"  # gzip-compressed NIfTI
    r = api.get(f"/reconstructions/{rec_id}/dicom", params={"patient_id": "phantom 1"})
    assert r.status_code == 200 and r.headers["content-type"] == "application/zip"
    with zipfile.ZipFile(io.BytesIO(r.content)) as zf:
        names = sorted(zf.namelist())
        assert len(names) == 24 and names[0] == f"{rec_id}/CT000001.dcm"
        ct = pydicom.dcmread(io.BytesIO(zf.read(names[0])))
    assert ct.Modality == "CT" and ct.PatientID == "phantom 1" and "FDK calibrated geometry" in ct.SeriesDescription
    assert (ct.Rows, ct.Columns) == (32, 32)
    r = api.get(f"/reconstructions/{rec_id}/dicom", params={"enhanced": True})
    with zipfile.ZipFile(io.BytesIO(r.content)) as zf:
        assert zf.namelist() == [f"{rec_id}/CT_ENHANCED.dcm"]
        assert int(pydicom.dcmread(io.BytesIO(zf.read(zf.namelist()[0]))).NumberOfFrames) == 24
    assert api.get(f"/reconstructions/{rec_id}/dicom", params={"water_mu_per_mm": 0}).status_code == 422
    assert [j["id"] for j in api.get("/jobs", params={"scan_id": scan_id}).json()] == [rec_id, cal_id]

    # the same reconstruction again: the name is taken in the scan file; replaced only when asked
    again = {"scan_id": scan_id, "algorithm": "fdk", "geometry": "calibrated", "shape": [8, 8, 8]}
    r = api.post("/reconstructions", role="analyst", json=again)
    assert r.status_code == 409 and "already has a reconstruction named 'fdk_calibrated'" in r.json()["message"]
    assert '"overwrite": true' in r.json()["message"]
    r = api.post("/reconstructions", role="analyst", json={**again, "overwrite": True})
    assert r.status_code == 202, r.text
    assert wait_for(api, f"/jobs/{r.json()['id']}", ended, 300)["state"] == "succeeded"

    # compared voxel for voxel: the 8-voxel volume resampled onto the 24 x 32 x 32 one's grid
    small = r.json()["id"]
    files_before = api.get(f"/reconstructions/{small}/files").json()
    r = api.get(f"/reconstructions/{small}/volume", params={"format": "npy", "grid_of": rec_id})
    assert r.status_code == 200 and np.load(io.BytesIO(r.content)).shape == (24, 32, 32)
    r = api.get(f"/reconstructions/{small}/volume", params={"grid_of": rec_id})
    (tmp_path / "on.nii.gz").write_bytes(r.content)
    (tmp_path / "own.nii.gz").write_bytes(api.get(f"/reconstructions/{rec_id}/volume").content)
    on, own = nib.load(tmp_path / "on.nii.gz"), nib.load(tmp_path / "own.nii.gz")
    assert on.shape == own.shape == (32, 32, 24) and np.allclose(on.affine, own.affine)
    assert api.get(f"/reconstructions/{small}/files").json() == files_before  # kept apart from the exports
    r = api.get(f"/reconstructions/{small}/volume", params={"grid_of": "0" * 16})
    assert r.status_code == 404 and "no reconstruction" in r.json()["message"]
    # and its slices (the viewer without WebGL): on the other's grid, in the other's grey window
    own_slice = api.get(f"/reconstructions/{small}/slices/axial")
    r = api.get(f"/reconstructions/{small}/slices/axial", params={"grid_of": rec_id, "index": 23})
    assert r.status_code == 200 and r.content[:4] == b"\x89PNG" and r.content != own_slice.content
    r = api.get(f"/reconstructions/{small}/slices/axial", params={"grid_of": rec_id, "index": 24})
    assert r.status_code == 404 and "0..23" in r.json()["message"]  # the other's 24 slices, not its own 8
    assert api.get(f"/reconstructions/{small}/slices/axial", params={"grid_of": "0" * 16}).status_code == 404
