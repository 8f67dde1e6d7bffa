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
    assert plan["hand_spiral"] is None  # a spiral round the object would enter the keep-out zone: nothing to compare
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
    assert counted["hand_spiral"]["bbs"] == len(counted["bbs"])  # no keep-out: a spiral of as many BBs beside it


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
    ({"experiment": "A", "frames": 20, "detector_px": 64,  # the whole turn, written 0 to 360
      "keep_out": [{"angle_from_deg": 0, "angle_to_deg": 360, "z_min_mm": -500, "z_max_mm": 500}]}, 422,
     "cover the whole surface"),
    ({"experiment": "A", "keep_out": [{"angle_from_deg": 30, "angle_to_deg": 30, "z_min_mm": -5, "z_max_mm": 5}]}, 422,
     "make no patch"),
])
def test_bad_plan_requests_are_refused_in_one_line(shared_api: Any, body: dict[str, Any], status: int, needle: str) -> None:
    r = shared_api.post("/plans/bbs", role="analyst", json=body)
    assert r.status_code == status and needle in r.text, r.text


def test_numbers_that_are_not_finite_are_refused_by_name(shared_api: Any) -> None:
    """Python's JSON (and so many clients) writes NaN and Infinity; every request model refuses them by name."""
    for body, needle in (('{"experiment": "A", "noise_px": NaN}', "noise_px: Input should be a finite number"),
                         ('{"experiment": "A", "keep_out": [{"angle_from_deg": Infinity, "angle_to_deg": 10, '
                          '"z_min_mm": 0, "z_max_mm": 1}]}', "keep_out.0.angle_from_deg: Input should be a finite number")):
        r = shared_api.post("/plans/bbs", role="analyst", content=body, headers={"Content-Type": "application/json"})
        assert r.status_code == 422 and needle in r.text, r.text


def test_an_unknown_plan_is_404(shared_api: Any) -> None:
    assert shared_api.get("/plans/bbs/0123456789ab").status_code == 404
    assert shared_api.get("/plans/bbs/..%2Fsecrets/picture").status_code == 404


def test_a_plan_on_a_prior_reconstructions_surface(make_api: Any) -> None:
    """A succeeded reconstruction of the object (here a 62 mm acrylic cylinder written as one) is its real surface."""
    import numpy as np

    from tests.app.service.test_jobs import _complete_scan

    api = make_api()
    scan_id = _complete_scan(api)
    job_id = "r000000000000001"
    api.service.store.add_job(job_id, kind="reconstruction", scan_id=scan_id, params={"algorithm": "fdk"}, owner="t")
    z, y, x = np.meshgrid(np.arange(-70.0, 71.0, 2.0), np.arange(-80.0, 81.0, 2.0), np.arange(-80.0, 81.0, 2.0),
                          indexing="ij")
    volume = np.where((np.hypot(x, y) <= 62.0) & (np.abs(z) <= 60.0), 0.0228, 0.0).astype(np.float32)
    folder = api.service.jobs.job_dir(job_id)
    folder.mkdir(parents=True, exist_ok=True)
    np.save(folder / "volume.npy", volume)
    api.service.store.update_job(job_id, state="succeeded", result={"voxel_mm": [2.0, 2.0, 2.0],
                                                                    "origin_mm": [-80.0, -80.0, -70.0]})
    body = {"experiment": "A", "frames": 60, "detector_px": 192, "bbs": 6, "surface_reconstruction_id": job_id}
    r = api.post("/plans/bbs", role="analyst", json=body)
    assert r.status_code == 201, r.text
    plan = r.json()
    assert plan["surface"]["kind"] == "outline" and plan["surface"]["source"].startswith(f"reconstruction {job_id} >")
    radii = [np.hypot(*b["xyz_mm"][:2]) for b in plan["bbs"]]
    assert np.allclose(radii, 62.0 + plan["bb_diameter_mm"] / 2, atol=2.0), radii
    r = api.post("/plans/bbs", role="analyst", json={**body, "surface_threshold_per_mm": 5.0})
    assert r.status_code == 422 and "no voxel above the threshold" in r.json()["message"]
    r = api.post("/plans/bbs", role="analyst", json={**body, "surface_reconstruction_id": "nosuchjob"})
    assert r.status_code == 404
