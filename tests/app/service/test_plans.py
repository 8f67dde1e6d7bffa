"""``/plans/bbs``: a BB plan queued, made in the background, kept, listed and read back (its JSON and picture);
bad requests refused at once, plans that cannot be made failed with the reason, plans cancelled, and plans a
stopped service left unmade marked failed."""

from __future__ import annotations

import json
import time
from typing import Any

import pytest

pytestmark = pytest.mark.timeout(180)

#: a plan that takes minutes (the fewest BBs for a worst view of 0.001 px over 2000 views): to see one being made
LONG = {"experiment": "A", "frames": 2000, "detector_px": 768, "target_px": 0.001, "max_bbs": 40}


def wait_for_plan(api: Any, plan_id: str, timeout_s: float = 120.0) -> dict[str, Any]:
    """``GET /plans/bbs/{id}`` once it is no longer planning."""
    deadline = time.monotonic() + timeout_s
    while True:
        plan = api.get(f"/plans/bbs/{plan_id}").json()
        if plan["state"] != "planning":
            return plan  # type: ignore[no-any-return]
        assert time.monotonic() < deadline, plan
        time.sleep(0.2)


def make_plan(api: Any, body: dict[str, Any]) -> dict[str, Any]:
    """Queue a plan (202 and its Location) and wait until it is done."""
    r = api.post("/plans/bbs", role="analyst", json=body)
    assert r.status_code == 202, r.text
    queued = r.json()
    assert queued["state"] == "planning" and r.headers["Location"] == f"/plans/bbs/{queued['id']}"
    plan = wait_for_plan(api, queued["id"])
    assert plan["state"] == "done", plan
    return plan


def test_a_plan_is_made_kept_and_read_back(shared_api: Any) -> None:
    api = shared_api
    body = {
        "experiment": "A",
        "frames": 60,
        "detector_px": 192,
        "bbs": 6,
        "keep_out": [{"angle_from_deg": 300, "angle_to_deg": 60, "z_min_mm": -80, "z_max_mm": 80}],
    }
    assert api.post("/plans/bbs", role="viewer", json=body).status_code == 403
    plan = make_plan(api, body)
    assert len(plan["bbs"]) == 6 and plan["views"] == 60 and plan["predicted"]["under_determined"] == 0
    assert all(60.0 < b["angle_deg"] < 300.0 for b in plan["bbs"])  # outside the keep-out zone
    assert plan["experiment_placement"]["bbs"] == 8 and len(plan["per_view"]["predicted_px"]) == 60
    assert plan["hand_spiral"] is None  # a spiral round the object would enter the keep-out zone: nothing to compare
    assert plan["time"]["expected_s"] > 0 and plan["time"]["elapsed_s"] > 0
    assert api.get(f"/plans/bbs/{plan['id']}").json() == plan
    picture = api.get(f"/plans/bbs/{plan['id']}/picture")
    assert picture.status_code == 200 and picture.content[:4] == b"\x89PNG"
    listed = api.get("/plans/bbs").json()
    assert listed[0]["id"] == plan["id"] and listed[0]["bbs"] == 6 and listed[0]["experiment"] == "A"
    assert listed[0]["state"] == "done"

    counted = make_plan(api, {"experiment": "A", "frames": 60, "detector_px": 192, "target_px": 0.3, "max_bbs": 8})
    suggestion = counted["count_suggestion"]
    assert suggestion["target_px"] == 0.3 and set(suggestion["tried"]) <= {str(n) for n in range(4, 9)}
    if suggestion["n_bbs"] is not None:
        assert len(counted["bbs"]) == suggestion["n_bbs"]
    assert counted["hand_spiral"]["bbs"] == len(counted["bbs"])  # no keep-out: a spiral of as many BBs beside it


def test_a_plan_on_a_shape_by_parameters(shared_api: Any) -> None:
    plan = make_plan(
        shared_api,
        {
            "experiment": "A",
            "frames": 40,
            "detector_px": 128,
            "bbs": 6,
            "surface_shape": "ellipsoid:70,60,90",
            "errors": "bench",
        },
    )
    assert plan["motion_errors"] == {"profile": "bench", "samples": 3}
    assert plan["surface"] == {
        "kind": "ellipsoid",
        "a_mm": 70.0,
        "b_mm": 60.0,
        "c_mm": 90.0,
        "z_min_mm": -81.0,
        "z_max_mm": 81.0,
    }
    for bb in plan["bbs"]:  # on the ellipsoid, a BB's radius outside it
        x, y, z = bb["xyz_mm"]
        assert (x / 70.0) ** 2 + (y / 60.0) ** 2 + (z / 90.0) ** 2 > 1.0 and abs(bb["height_mm"]) <= 81.0
    for shape, needle in (
        ("ellipsoid:70,60", "expected ellipsoid:A,B,C"),
        ("cylinder:50,-5:5,3", "expected cylinder"),
        ("ellipsoid:70,60,90,0:200", "within the ellipsoid"),
        ("/etc/passwd", "surface_shape"),
        ("cylinder:0,-5:5", "semi-axes must be in (0, 1000] mm"),
    ):
        r = shared_api.post("/plans/bbs", role="analyst", json={"experiment": "A", "surface_shape": shape})
        assert r.status_code == 422 and needle in r.text, (shape, r.text)
    r = shared_api.post(
        "/plans/bbs",
        role="analyst",
        json={"experiment": "A", "surface_shape": "cylinder:50,-5:5", "surface_id": "0123456789ab"},
    )
    assert r.status_code == 422 and "not surface_id and surface_shape" in r.text, r.text


def test_a_plan_being_made_is_listed_and_can_be_cancelled(shared_api: Any) -> None:
    api = shared_api
    r = api.post("/plans/bbs", role="analyst", json=LONG)
    assert r.status_code == 202, r.text
    plan_id = r.json()["id"]
    record = api.get(f"/plans/bbs/{plan_id}").json()
    assert record["state"] == "planning" and record["views"] == 2000 and record["target_px"] == 0.001
    assert record["owner"] == "test-analyst"
    listed = {p["id"]: p for p in api.get("/plans/bbs").json()}
    assert listed[plan_id]["state"] == "planning" and listed[plan_id]["bbs"] is None
    r = api.get(f"/plans/bbs/{plan_id}/picture")
    assert r.status_code == 409 and "is planning" in r.json()["message"]
    assert api.post(f"/plans/bbs/{plan_id}/cancel", role="viewer").status_code == 403
    deadline = time.monotonic() + 60.0  # let it start: the process is killed, not just taken off the queue
    while "expected_s" not in (record := api.get(f"/plans/bbs/{plan_id}").json()):  # said once prepared
        assert time.monotonic() < deadline, record
        time.sleep(0.2)
    assert record["progress"]["stage"] in ("prepare", "count", "plan") and record["progress"]["total"] > 0, record
    assert record["expected_s"] > 0, record
    r = api.post(f"/plans/bbs/{plan_id}/cancel", role="analyst")
    assert r.status_code == 202 and r.json()["state"] == "cancelled", r.text
    assert r.json()["reason"] == "cancelled by test-analyst"
    assert api.get(f"/plans/bbs/{plan_id}").json()["state"] == "cancelled"
    r = api.post(f"/plans/bbs/{plan_id}/cancel", role="analyst")
    assert r.status_code == 409 and "already ended" in r.json()["message"]
    assert api.post("/plans/bbs/0123456789ab/cancel", role="analyst").status_code == 404
    # the next plan is made as if nothing had happened
    assert len(make_plan(api, {"experiment": "A", "frames": 40, "detector_px": 128, "bbs": 5})["bbs"]) == 5


def test_plans_wait_their_turn_and_a_full_queue_is_refused(shared_api: Any) -> None:
    from orbitct_app.service.jobs.bbplans import MAX_PLANS_WAITING

    api = shared_api
    answers = [api.post("/plans/bbs", role="analyst", json=LONG) for _ in range(MAX_PLANS_WAITING)]
    assert all(r.status_code == 202 for r in answers), [r.text for r in answers]
    ids = [r.json()["id"] for r in answers]
    r = api.post("/plans/bbs", role="analyst", json=LONG)
    assert r.status_code == 409 and "already waiting or being made" in r.json()["message"], r.text
    for plan_id in reversed(ids):  # the waiting ones first: each is taken off the queue, the last one killed
        assert api.post(f"/plans/bbs/{plan_id}/cancel", role="analyst").json()["state"] == "cancelled"


def test_a_plan_that_cannot_be_made_fails_with_the_reason(shared_api: Any) -> None:
    r = shared_api.post(
        "/plans/bbs",
        role="analyst",
        json={
            "experiment": "A",
            "frames": 20,
            "detector_px": 64,
            "bbs": 40,
            "keep_out": [{"angle_from_deg": 0, "angle_to_deg": 270, "z_min_mm": -500, "z_max_mm": 500}],
        },
    )
    assert r.status_code == 202, r.text
    plan = wait_for_plan(shared_api, r.json()["id"])
    assert plan["state"] == "failed" and "40 BBs 25 mm apart do not fit on the surface" in plan["reason"], plan
    listed = {p["id"]: p for p in shared_api.get("/plans/bbs").json()}
    assert listed[plan["id"]]["state"] == "failed" and "do not fit" in listed[plan["id"]]["reason"]


def test_a_plan_the_service_stopped_is_failed_after_the_restart(make_api: Any) -> None:
    api = make_api()
    plan_id = api.post("/plans/bbs", role="analyst", json=LONG).json()["id"]
    api.client.__exit__(None, None, None)  # the service stops while the plan is being made
    assert not any(p.name.startswith("orbitct-plan-") for p in __import__("multiprocessing").active_children())
    # a service killed outright leaves its plan's record planning (and maybe half a plan): the next one says so
    (api.data_dir / "plans" / "0123456789ab.state").write_text(
        json.dumps(
            {
                "id": "0123456789ab",
                "state": "planning",
                "owner": "t",
                "created": "2026-01-01T00:00:00.000+00:00",
                "experiment": "A",
                "orbit": "sawtooth",
                "views": 20,
                "bbs": 4,
            }
        )
    )
    (api.data_dir / "plans" / ".0123456789ab.partial").mkdir()
    again = make_api(api.data_dir)
    for stopped in (plan_id, "0123456789ab"):
        plan = again.get(f"/plans/bbs/{stopped}").json()
        assert plan["state"] == "failed" and plan["reason"] == "the service stopped while the plan was being made", plan
    assert not list((api.data_dir / "plans").glob(".*.partial"))


@pytest.mark.parametrize(
    ("body", "status", "needle"),
    [
        ({"experiment": "D"}, 422, "experiment"),
        ({"experiment": "A", "bbs": 3}, 422, "bbs"),
        ({"experiment": "A", "errors": "wobbly"}, 422, "errors"),
        (
            {"experiment": "A", "keep_out": [{"angle_from_deg": 0, "angle_to_deg": 90, "z_min_mm": 5, "z_max_mm": 1}]},
            422,
            "must be below",
        ),
        ({"experiment": "A", "orbit": "nosuch", "frames": 20}, 422, "nosuch"),
        (
            {
                "experiment": "A",
                "frames": 20,
                "detector_px": 64,
                "keep_out": [
                    {"angle_from_deg": 0, "angle_to_deg": 180, "z_min_mm": -500, "z_max_mm": 500},
                    {"angle_from_deg": 180, "angle_to_deg": 0, "z_min_mm": -500, "z_max_mm": 500},
                ],
            },
            422,
            "cover the whole surface",
        ),
        (
            {
                "experiment": "A",
                "frames": 20,
                "detector_px": 64,  # the whole turn, written 0 to 360
                "keep_out": [{"angle_from_deg": 0, "angle_to_deg": 360, "z_min_mm": -500, "z_max_mm": 500}],
            },
            422,
            "cover the whole surface",
        ),
        (
            {
                "experiment": "A",
                "keep_out": [{"angle_from_deg": 30, "angle_to_deg": 30, "z_min_mm": -5, "z_max_mm": 5}],
            },
            422,
            "make no patch",
        ),
    ],
)
def test_bad_plan_requests_are_refused_in_one_line(
    shared_api: Any, body: dict[str, Any], status: int, needle: str
) -> None:
    r = shared_api.post("/plans/bbs", role="analyst", json=body)
    assert r.status_code == status and needle in r.text, r.text


def test_numbers_that_are_not_finite_are_refused_by_name(shared_api: Any) -> None:
    """Python's JSON (and so many clients) writes NaN and Infinity; every request model refuses them by name."""
    for body, needle in (
        ('{"experiment": "A", "noise_px": NaN}', "noise_px: Input should be a finite number"),
        (
            '{"experiment": "A", "keep_out": [{"angle_from_deg": Infinity, "angle_to_deg": 10, '
            '"z_min_mm": 0, "z_max_mm": 1}]}',
            "keep_out.0.angle_from_deg: Input should be a finite number",
        ),
    ):
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
    z, y, x = np.meshgrid(
        np.arange(-70.0, 71.0, 2.0), np.arange(-80.0, 81.0, 2.0), np.arange(-80.0, 81.0, 2.0), indexing="ij"
    )
    volume = np.where((np.hypot(x, y) <= 62.0) & (np.abs(z) <= 60.0), 0.0228, 0.0).astype(np.float32)
    folder = api.service.jobs.job_dir(job_id)
    folder.mkdir(parents=True, exist_ok=True)
    np.save(folder / "volume.npy", volume)
    api.service.store.update_job(
        job_id, state="succeeded", result={"voxel_mm": [2.0, 2.0, 2.0], "origin_mm": [-80.0, -80.0, -70.0]}
    )
    body = {"experiment": "A", "frames": 60, "detector_px": 192, "bbs": 6, "surface_reconstruction_id": job_id}
    plan = make_plan(api, body)
    assert plan["surface"]["kind"] == "outline" and plan["surface"]["source"].startswith(f"reconstruction {job_id} >")
    radii = [np.hypot(*b["xyz_mm"][:2]) for b in plan["bbs"]]
    assert np.allclose(radii, 62.0 + plan["bb_diameter_mm"] / 2, atol=2.0), radii
    r = api.post("/plans/bbs", role="analyst", json={**body, "surface_threshold_per_mm": 5.0})
    assert r.status_code == 422 and "no voxel above the threshold" in r.json()["message"]
    r = api.post("/plans/bbs", role="analyst", json={**body, "surface_reconstruction_id": "nosuchjob"})
    assert r.status_code == 404
