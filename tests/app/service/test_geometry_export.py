"""``GET /scans/{id}/geometry/export``: the document ``orbitct export <toolkit>`` and the Python API write, with the
same refusals."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from click.testing import CliRunner

from orbitct.toolkits import GeometryExportOptions
from orbitct_app.cli.main import cli
from recon.geometry_export import export_scan_geometry
from tests.app.service.conftest import Api
from tests.helpers.service import failed_scan_file, register_scan


@pytest.fixture
def failed(api: Api, tmp_path: Path) -> tuple[str, Path]:
    """A complete scan in the service whose calibrated geometry failed its check: its id and its file."""
    scan_id = register_scan(api, failed_scan_file(tmp_path / "failed.h5"))
    return scan_id, api.data_dir / "scans" / f"{scan_id}.h5"


@pytest.mark.parametrize("toolkit", ["tigre", "rtk"])
def test_rest_cli_and_python_write_the_same_document(
    api: Api, failed: tuple[str, Path], tmp_path: Path, toolkit: str
) -> None:
    scan_id, path = failed
    r = api.get(f"/scans/{scan_id}/geometry/export", params={"toolkit": toolkit, "geometry": "nominal"})
    assert r.status_code == 200, r.text
    suffix = ".xml" if toolkit == "rtk" else ".json"
    assert r.headers["content-disposition"] == f'attachment; filename="{scan_id}-{toolkit}{suffix}"'
    python = export_scan_geometry(
        path, GeometryExportOptions(toolkit=toolkit, geometry="nominal"), name=f"scan {scan_id}"
    )
    assert r.text == python.text
    out = tmp_path / f"cli{suffix}"
    res = CliRunner().invoke(cli, ["export", toolkit, str(path), "--out", str(out), "--geometry", "nominal"])
    assert res.exit_code == 0, res.output
    if toolkit == "rtk":
        assert out.read_text() == r.text and r.headers["content-type"].startswith("application/xml")
    else:  # the CLI names the file it read, the service the scan
        cli_doc, rest_doc = json.loads(out.read_text()), r.json()
        assert rest_doc.pop("orbitct") == {"scan": f"scan {scan_id}", "geometry": "nominal"}
        assert cli_doc.pop("orbitct")["geometry"] == "nominal" and cli_doc == rest_doc
        assert rest_doc["views"] == 40


def test_a_failed_geometry_is_refused_until_accepted(api: Api, failed: tuple[str, Path]) -> None:
    scan_id, _ = failed
    r = api.get(f"/scans/{scan_id}/geometry/export", params={"toolkit": "astra"})
    body = r.json()
    assert r.status_code == 409 and body["error"] == "failed_quality_check", body
    assert "failed its quality check (5 of 40 view(s) failed)" in body["message"]
    assert "accept_failed_geometry=true" in body["advice"]
    r = api.get(f"/scans/{scan_id}/geometry/export", params={"toolkit": "astra", "accept_failed_geometry": "true"})
    assert r.status_code == 200 and r.json()["orbitct"]["geometry"] == "calibrated"


def test_a_missing_geometry_and_an_unknown_toolkit_say_what_to_do(api: Api, failed: tuple[str, Path]) -> None:
    scan_id, _ = failed
    r = api.get(f"/scans/{scan_id}/geometry/export", params={"toolkit": "leap", "geometry": "truth"})
    assert r.status_code == 404 and r.json()["message"].startswith(f"scan {scan_id} has no truth geometry"), r.text
    assert "geometry=nominal" in r.json()["advice"]
    r = api.get(f"/scans/{scan_id}/geometry/export", params={"toolkit": "mlem"})
    assert r.status_code == 422 and r.json()["error"] == "invalid_parameters", r.text
    assert api.get("/scans/0123456789abcdef/geometry/export", params={"toolkit": "cil"}).status_code == 404
