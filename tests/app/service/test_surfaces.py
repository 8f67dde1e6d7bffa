"""``/surfaces``: a surface mesh uploaded, kept, listed, and planned on (``POST /plans/bbs`` with ``surface_id``);
bad uploads refused in one line."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from tests.app.service.test_plans import make_plan

pytestmark = pytest.mark.timeout(180)


def _cylinder_stl(radius_mm: float = 62.0, half_height_mm: float = 60.0) -> bytes:
    import trimesh

    mesh = trimesh.creation.cylinder(radius=radius_mm, height=2 * half_height_mm, sections=128)
    return bytes(mesh.export(file_type="stl"))


def test_a_mesh_is_uploaded_listed_and_planned_on(shared_api: Any) -> None:
    api = shared_api
    data = _cylinder_stl()
    assert api.post("/surfaces?name=leg.stl", role="viewer", content=data).status_code == 403
    r = api.post("/surfaces?name=leg.stl", role="analyst", content=data, headers={"Content-Type": "model/stl"})
    assert r.status_code == 201, r.text
    kept = r.json()
    assert r.headers["Location"] == f"/surfaces/{kept['id']}" and kept["name"] == "leg.stl"
    assert kept["surface"]["kind"] == "outline" and kept["surface"]["source"] == "leg.stl"
    assert np.allclose(kept["surface"]["radius_mm"], 62.0, atol=1.0)
    assert api.get(f"/surfaces/{kept['id']}").json() == kept
    assert api.get("/surfaces").json()[0] == kept
    body = {"experiment": "A", "frames": 60, "detector_px": 192, "bbs": 6, "surface_id": kept["id"]}
    plan = make_plan(api, body)
    assert plan["surface"]["source"] == "leg.stl"
    radii = [np.hypot(*b["xyz_mm"][:2]) for b in plan["bbs"]]
    assert np.allclose(radii, 62.0 + plan["bb_diameter_mm"] / 2, atol=1.5), radii
    both = api.post("/plans/bbs", role="analyst", json={**body, "surface_reconstruction_id": "r1"})
    assert both.status_code == 422 and "not surface_id and surface_reconstruction_id" in both.text
    assert api.post("/plans/bbs", role="analyst", json={**body, "surface_id": "0123456789ab"}).status_code == 404


@pytest.mark.parametrize(
    ("name", "content", "status", "needle"),
    [
        ("leg.txt", b"solid x", 422, "is not a mesh file; upload a"),
        ("leg.stl", b"", 422, "the request body is empty; send the mesh file"),
        ("leg.stl", b"\x00\x01 this is no mesh at all \xff" * 8, 422, "leg.stl"),
        ("../leg.stl", b"solid x", 422, "name"),
    ],
)
def test_bad_uploads_are_refused_in_one_line(
    shared_api: Any, name: str, content: bytes, status: int, needle: str
) -> None:
    r = shared_api.post(f"/surfaces?name={name}", role="analyst", content=content)
    assert r.status_code == status and needle in r.text, r.text
    assert "/tmp" not in r.text and "surfaces/" not in r.text  # the service's own paths stay inside


def test_an_upload_over_the_limit_is_refused_before_it_is_read(make_api: Any) -> None:
    api = make_api(max_upload_bytes=4096, max_body_bytes=1024)
    r = api.post("/surfaces?name=leg.stl", role="analyst", content=b"x" * 5000)
    assert r.status_code == 413 and "4096" in r.text
    assert (
        api.post(
            "/plans/bbs",
            role="analyst",
            content=b"{" + b" " * 2000 + b"}",
            headers={"Content-Type": "application/json"},
        ).status_code
        == 413
    )  # other routes keep theirs
    assert api.get("/surfaces/0123456789ab").status_code == 404 and api.get("/surfaces/..%2Fx").status_code == 404
