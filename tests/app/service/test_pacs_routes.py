"""``/pacs`` against a real Orthanc: the settings' nodes, find, import a C-arm run as a scan, send a volume back."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pydicom
import pytest

from orbitct_app.pacs import find_series, get_series, send
from tests.app.service.test_jobs import _wait
from tests.app.test_pacs import _carm_scan
from tests.helpers.orthanc import orthanc
from tests.helpers.service import free_port

pytestmark = [pytest.mark.system, pytest.mark.slow]


def test_runs_come_in_as_scans_and_volumes_go_out_through_the_configured_node(make_api: Any, tmp_path: Path) -> None:
    from orbitct.scanfile.xa import write_xa_run

    run = write_xa_run(_carm_scan(tmp_path / "carm.h5"), tmp_path / "xa" / "run.dcm", patient_id="REST-1")
    down = free_port()  # nothing listens there
    with orthanc(tmp_path / "orthanc") as node:
        api = make_api(pacs_nodes={"lab": str(node), "down": f"dicom://NOBODY@127.0.0.1:{down}"})
        assert api.get("/pacs").json() == [
            {"name": "down", "ae_title": "NOBODY", "host": "127.0.0.1", "port": down},
            {"name": "lab", "ae_title": "ORTHANC", "host": "127.0.0.1", "port": node.port},
        ]
        send([run], node)
        found = api.get("/pacs/lab/series", params={"modality": "XA", "patient_id": "REST-1"}).json()
        assert len(found) == 1 and found[0]["modality"] == "XA"
        series = found[0]

        body = {"study_uid": series["study_uid"], "series_uids": [series["series_uid"]], "name": "from the PACS"}
        assert api.post("/pacs/lab/import", role="viewer", json=body).status_code == 403
        r = api.post("/pacs/lab/import", role="analyst", json=body)
        assert r.status_code == 201, r.text
        scan_id = r.json()["id"]
        assert r.headers["location"] == f"/scans/{scan_id}" and r.json()["frames"] == 12 and r.json()["assumed"]
        assert any("read as offsets from the first frame" in line for line in r.json()["assumed"]), r.json()
        wrong = api.post("/pacs/lab/import", role="analyst", json={**body, "angle_increments": "absolute"})
        assert wrong.status_code == 422 and "the increments are not absolute; try auto" in wrong.json()["message"]
        assert api.post("/pacs/lab/import", role="analyst", json={**body, "angle_increments": "x"}).status_code == 422
        scan = api.get(f"/scans/{scan_id}").json()
        assert scan["state"] == "complete" and scan["name"] == "from the PACS"
        assert "nominal" in scan["summary"]["geometries"]

        r = api.post(
            "/reconstructions",
            role="analyst",
            json={"scan_id": scan_id, "algorithm": "fdk", "geometry": "nominal", "shape": [8, 16, 16]},
        )
        assert r.status_code == 202, r.text
        rec = r.json()["id"]
        assert _wait(api, rec, timeout_s=120.0)["state"] == "succeeded"
        r = api.post("/pacs/lab/store", role="analyst", json={"reconstruction_id": rec, "patient_id": "REST-1"})
        assert r.status_code == 200, r.text
        assert r.json() == {"node": "lab", "stored": 8}
        ct = find_series(node, PatientID="REST-1", Modality="CT")
        assert len(ct) == 1 and ct[0]["NumberOfSeriesRelatedInstances"] == "8"
        r = api.post(
            "/pacs/lab/store", role="analyst", json={"reconstruction_id": rec, "patient_id": "REST-2", "enhanced": True}
        )
        assert r.json() == {"node": "lab", "stored": 1}, r.text
        ect = find_series(node, PatientID="REST-2", Modality="CT")
        pulled = get_series(node, ect[0]["StudyInstanceUID"], ect[0]["SeriesInstanceUID"], tmp_path / "ect")
        enhanced_ct = pydicom.dcmread(pulled[0])
        assert int(enhanced_ct.NumberOfFrames) == 8 and "left and right" in enhanced_ct.ImageComments  # the caveat

        r = api.get("/pacs/nowhere/series")
        assert r.status_code == 404 and "a configured node (down, lab)" in r.json()["message"]
        r = api.get("/pacs/down/series")
        assert r.status_code == 502 and "NOBODY" in r.json()["message"] and r.json()["error"] == "bad_gateway"
        r = api.post("/pacs/lab/import", role="analyst", json={**body, "series_uids": ["1.2.3.4"]})
        assert r.status_code == 502 and "retrieving series 1.2.3.4 failed" in r.json()["message"]
