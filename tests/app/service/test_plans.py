"""``/plans/bbs``: a BB plan made, kept, listed and read back (its JSON and picture), and bad requests refused."""

from __future__ import annotations

from typing import Any

import pytest

pytestmark = pytest.mark.timeout(180)


def test_a_plan_is_made_kept_and_read_back(shared_api: Any) -> None:
    api = shared_api
    body = {"experiment": "A", "frames": 60, "detector_px": 192, "bbs": 6,
            "keep_out": [{"angle_from_deg": 300, "angle_to_deg": 60, "z_min_mm": -80, "z_max_mm": 80}]}
    assert api.post("/plans/bbs", role="viewer", json=body).status_code == 403
    r = api.post("/plans/bbs", role="analyst", json=body)
    assert r.status_code == 201, r.text
    plan = r.json()
    assert r.headers["Location"] == f"/plans/bbs/{plan['id']}"
    assert len(plan["bbs"]) == 6 and plan["views"] == 60 and plan["predicted"]["under_determined"] == 0
    assert all(60.0 < b["angle_deg"] < 300.0 for b in plan["bbs"])  # outside the keep-out zone
    assert plan["experiment_placement"]["bbs"] == 8 and len(plan["per_view"]["predicted_px"]) == 60
    assert api.get(f"/plans/bbs/{plan['id']}").json() == plan
    picture = api.get(f"/plans/bbs/{plan['id']}/picture")
    assert picture.status_code == 200 and picture.content[:4] == b"\x89PNG"
    listed = api.get("/plans/bbs").json()
    assert listed[0]["id"] == plan["id"] and listed[0]["bbs"] == 6 and listed[0]["experiment"] == "A"

    counted = api.post("/plans/bbs", role="analyst", json={"experiment": "A", "frames": 60, "detector_px": 192,
                                                            "target_px": 0.3, "max_bbs": 8}).json()
    suggestion = counted["count_suggestion"]
    assert suggestion["target_px"] == 0.3 and set(suggestion["tried"]) <= {str(n) for n in range(4, 9)}
    if suggestion["n_bbs"] is not None:
        assert len(counted["bbs"]) == suggestion["n_bbs"]


@pytest.mark.parametrize(("body", "status", "needle"), [
    ({"experiment": "D"}, 422, "experiment"),
    ({"experiment": "A", "bbs": 3}, 422, "bbs"),
    ({"experiment": "A", "keep_out": [{"angle_from_deg": 0, "angle_to_deg": 90, "z_min_mm": 5, "z_max_mm": 1}]}, 422,
     "must be below"),
    ({"experiment": "A", "orbit": "nosuch", "frames": 20}, 422, "nosuch"),
    ({"experiment": "A", "frames": 20, "detector_px": 64,
      "keep_out": [{"angle_from_deg": 0, "angle_to_deg": 180, "z_min_mm": -500, "z_max_mm": 500},
                   {"angle_from_deg": 180, "angle_to_deg": 0, "z_min_mm": -500, "z_max_mm": 500}]}, 422,
     "cover the whole surface"),
])
def test_bad_plan_requests_are_refused_in_one_line(shared_api: Any, body: dict[str, Any], status: int, needle: str) -> None:
    r = shared_api.post("/plans/bbs", role="analyst", json=body)
    assert r.status_code == status and needle in r.text, r.text


def test_an_unknown_plan_is_404(shared_api: Any) -> None:
    assert shared_api.get("/plans/bbs/0123456789ab").status_code == 404
    assert shared_api.get("/plans/bbs/..%2Fsecrets/picture").status_code == 404
