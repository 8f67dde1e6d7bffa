"""The BB planner's prediction: usable BBs per view, and the predicted calibration error against a measured one."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from calib.plan import (
    KeepOut,
    hand_spiral,
    metal_of,
    placement_score,
    plan_placement,
    predict_placement,
    suggest_bb_count,
    usable_bbs,
)
from calib.surfaces import EllipticCylinder, address_angle, polar_angle
from orbitct.phantoms.primitives import sphere
from orbitct.progress import ProgressEvent
from tests.helpers.calib_scans import sawtooth, spiral_markers

D_MM = 3.17


def test_bbs_off_the_panel_overlapping_or_behind_metal_are_not_usable() -> None:
    g = sawtooth(60, 256)
    xyz = spiral_markers(8)
    usable, uv = usable_bbs(g, xyz, D_MM)
    assert usable.all(axis=1).mean() > 0.5  # most views see all eight
    twin = np.vstack([xyz, xyz[0] + [0.0, 0.0, 2.0]])  # a ninth BB 2 mm above the first: one blob in every view
    usable, _ = usable_bbs(g, twin, D_MM)
    assert not usable[:, 0].any() and not usable[:, 8].any()
    far = np.vstack([xyz, [[0.0, 0.0, 400.0]]])  # far above the field of view
    usable, _ = usable_bbs(g, far, D_MM)
    assert not usable[:, 8].any()
    screw = sphere(0.3 * xyz[2], 6.0, material="titanium", label="screw")  # metal between the axis and BB 2
    usable, _ = usable_bbs(g, xyz, D_MM, metal=[screw])
    assert 0 < (~usable[:, 2]).sum() < g.n_views and usable[:, 5].sum() >= usable_bbs(g, xyz, D_MM)[0][:, 5].sum() - 2


def test_a_bb_counts_only_where_it_stays_usable_under_the_orbits_motion_errors() -> None:
    from orbitct.errorprofiles import RigidErrors

    g = sawtooth(60, 256)
    xyz = np.vstack([spiral_markers(8), [[0.0, 0.0, 118.0]]])  # a ninth BB near the top of the field of view
    nominal = predict_placement(g, xyz, D_MM)
    near_top = usable_bbs(g, xyz, D_MM)[0][:, 8]
    assert near_top.sum() >= 50, "the test wants the ninth BB usable in most nominal views"
    lifted = RigidErrors(np.zeros((60, 3)), np.tile([0.0, 0.0, 30.0], (60, 1))).apply_to_geometry(g)  # 30 mm up
    moved = predict_placement(g, xyz, D_MM, moved=[lifted])
    assert (moved.n_bbs <= nominal.n_bbs).all() and (moved.n_bbs < nominal.n_bbs).sum() >= 30
    assert moved.usable[:, 8].sum() <= 5  # it leaves the panel in (nearly) every moved view: there it does not count
    assert np.array_equal(predict_placement(g, xyz, D_MM, moved=[g]).n_bbs, nominal.n_bbs)  # no motion, no change


def test_more_bbs_predict_a_smaller_error_and_three_leave_every_view_under_determined() -> None:
    g = sawtooth(120, 256)
    xyz = spiral_markers(10)
    few, many = predict_placement(g, xyz[:5], D_MM), predict_placement(g, xyz, D_MM)
    assert np.nanmedian(many.predicted_px) < np.nanmedian(few.predicted_px)
    assert predict_placement(g, xyz, D_MM, noise_px=0.2).summary()["predicted_px_median"] == pytest.approx(
        2 * many.summary()["predicted_px_median"]
    )  # linear in the centroid noise
    three = predict_placement(g, xyz[:3], D_MM)
    assert three.under_determined.size == g.n_views and np.isnan(three.predicted_px).all()


@pytest.mark.slow
def test_the_prediction_matches_a_calibration_of_the_same_placement(tmp_path: Path) -> None:
    """Experiment A with its own BBs, simulated and calibrated: the error predicted from the nominal orbit and the
    calibration's measured centroid noise is within a factor of 1.5 of the error measured against the truth."""
    import calib
    from calib.evaluate import similarity_aligned_error_px
    from orbitct.errorprofiles import make_profile
    from orbitct.phantoms.experiments import BB_SURFACES, experiment_phantom
    from orbitct.scanfile import ScanFile
    from orbitct.simulator.scan import simulate_scan

    ph = experiment_phantom("A", 0)
    path = tmp_path / "a.h5"
    simulate_scan(ph, out=path, n_frames=120, detector_px=256, errors=make_profile("bench", 0, angle_scale=120 / 500))
    res = calib.calibrate_scan(path)
    with ScanFile(path) as sf:
        proj = sf.projection_indices
        truth, nominal = sf.geometry("truth")[proj], sf.geometry("nominal")[proj]
    own = np.flatnonzero(res.view_status[proj] == 0)
    measured = similarity_aligned_error_px(res.geometry[proj][own], truth[own])[0]
    assert res.quality is not None
    pred = predict_placement(
        nominal,
        ph.markers_xyz,
        ph.marker_diameter_mm,
        noise_px=res.quality.attrs()["centroid_noise_px"],
        metal=metal_of(ph),
        surface=EllipticCylinder(*BB_SURFACES["A"]),
    )
    predicted = float(np.sqrt(np.nanmean(pred.predicted_px[own] ** 2)))
    print(f"predicted {predicted:.4f} px, measured {measured:.4f} px")
    assert 1 / 1.5 <= predicted / measured <= 1.5, (predicted, measured)


def test_cli_plans_bbs_writes_the_plan_and_its_picture_and_the_simulator_uses_it(tmp_path: Path) -> None:
    import json

    from click.testing import CliRunner

    from orbitct.scanfile import ScanFile
    from orbitct_app.cli.main import cli

    plan = tmp_path / "plan.json"
    r = CliRunner().invoke(
        cli, ["plan", "bbs", "-e", "A", "--frames", "60", "--detector-size", "192", "--bbs", "6", "--out", str(plan)]
    )
    assert r.exit_code == 0, r.output
    body = json.loads(plan.read_text())
    assert len(body["bbs"]) == 6 and body["predicted"]["under_determined"] == 0
    assert len(body["per_view"]["n_bbs"]) == 60 and plan.with_suffix(".png").stat().st_size > 10_000
    assert "planned (6 BBs): predicted error median" in r.output and "the experiment's own (8 BBs)" in r.output
    assert "a hand-made spiral (6 BBs)" in r.output and body["hand_spiral"]["bbs"] == 6
    assert body["noise_px"] == 0.1 and body["noise_model"]["shift_factor"] == 1.65  # what the prediction assumed
    scan = tmp_path / "planned.h5"
    r = CliRunner().invoke(
        cli,
        ["simulate", "-e", "A", "--frames", "20", "--detector-size", "64", "--bbs-from", str(plan), "--out", str(scan)],
    )
    assert r.exit_code == 0, r.output
    with ScanFile(scan) as sf:
        np.testing.assert_allclose(sf.truth_markers_xyz(), [b["xyz_mm"] for b in body["bbs"]])
    counted = tmp_path / "counted.json"
    r = CliRunner().invoke(
        cli,
        [
            "plan",
            "bbs",
            "-e",
            "A",
            "--frames",
            "60",
            "--detector-size",
            "192",
            "--target-px",
            "0.3",
            "--max-bbs",
            "8",
            "--keep-out",
            "0:90,-80:80",
            "--out",
            str(counted),
        ],
    )
    assert r.exit_code == 0, r.output
    body = json.loads(counted.read_text())
    suggestion = body["count_suggestion"]
    assert suggestion["target_px"] == 0.3 and "fewest BBs for 0.3 px in every view" in r.output
    if suggestion["n_bbs"] is not None:
        assert len(body["bbs"]) == suggestion["n_bbs"] and body["predicted"]["predicted_px_max"] <= 0.3
    assert body["keep_out"] == [{"angle_from_deg": 0.0, "angle_to_deg": 90.0, "z_min_mm": -80.0, "z_max_mm": 80.0}]
    assert all(not 0.0 <= b["angle_deg"] <= 90.0 for b in body["bbs"])
    r = CliRunner().invoke(cli, ["plan", "bbs", "-e", "A", "--keep-out", "0:90", "--out", str(tmp_path / "k.json")])
    assert r.exit_code == 2 and "FROM_DEG:TO_DEG,ZMIN_MM:ZMAX_MM" in r.output and "Traceback" not in r.output
    plan.write_text("{}")
    r = CliRunner().invoke(
        cli,
        [
            "simulate",
            "-e",
            "A",
            "--frames",
            "20",
            "--detector-size",
            "64",
            "--bbs-from",
            str(plan),
            "--out",
            str(tmp_path / "x.h5"),
        ],
    )
    assert r.exit_code == 2 and "not a BB plan" in r.output and "Traceback" not in r.output


def test_a_hand_made_spiral_climbs_one_turn_round_the_object_evenly() -> None:
    surface = EllipticCylinder(75.0, 75.0, -80.0, 80.0)
    xyz = hand_spiral(surface, 8, D_MM, seed=3)
    assert xyz.shape == (8, 3)
    np.testing.assert_allclose(np.hypot(xyz[:, 0], xyz[:, 1]), 75.0 + D_MM / 2)  # on the surface, a BB's radius out
    steps = np.degrees(np.diff(np.unwrap(np.arctan2(xyz[:, 1], xyz[:, 0])))) % 360.0
    assert np.all((steps > 45.0 - 20.0) & (steps < 45.0 + 20.0)), steps  # one turn, an eighth apart, give or take
    assert np.all(np.diff(xyz[:, 2]) > 0) and -80 < xyz[0, 2] < -50 and 50 < xyz[-1, 2] < 80
    assert not np.allclose(hand_spiral(surface, 8, D_MM, seed=4), xyz)  # each hand places them a little differently
    with pytest.raises(ValueError, match="keep-out"):  # one turn round the object crosses a patch of 120 degrees
        hand_spiral(surface, 8, D_MM, seed=3, keep_out=[KeepOut.parse("300:60,-80:80")])


def test_keep_out_zones_are_parsed_wrap_through_zero_and_stay_free_of_bbs() -> None:
    zone = KeepOut.parse("300:60,-20:10")
    assert zone == KeepOut(300.0, 60.0, -20.0, 10.0)
    inside = zone.contains(np.radians([330.0, 10.0, 59.0, 90.0, 10.0]), np.array([0.0, 0.0, 0.0, 0.0, 30.0]))
    assert inside.tolist() == [True, True, True, False, False]
    for bad, message in (
        ("300:60", "expected FROM_DEG"),
        ("a:b,1:2", "expected FROM_DEG"),
        ("0:90,10:5", "must be below"),
        ("30:30,0:1", "no patch"),
        ("0:720,0:1", None),
    ):
        if message is None:  # more than a turn: the whole turn
            assert KeepOut.parse(bad) == KeepOut(0.0, 360.0, 0.0, 1.0)
            continue
        with pytest.raises(ValueError, match=message):
            KeepOut.parse(bad)
    whole = KeepOut.parse("0:360,-20:10")  # the whole turn, not an empty patch
    assert whole.span_deg == 360.0 and whole.contains(np.radians([0.0, 90.0, 359.9]), np.zeros(3)).all()
    assert KeepOut.parse("-180:180,-20:10").span_deg == 360.0 and KeepOut.parse("10:360,0:1").span_deg == 350.0
    g = sawtooth(60, 256)
    surface = EllipticCylinder(60.0, 60.0, -40.0, 40.0)
    zones = (KeepOut(0.0, 180.0, -40.0, 40.0), KeepOut(180.0, 270.0, -40.0, 0.0))  # three quarters of the surface
    placed = plan_placement(g, surface, 5, D_MM, keep_out=zones, trials=30, rounds=1, min_spacing_mm=10.0)
    assert not any(z.contains(placed.angle_rad, placed.z_mm).any() for z in zones)
    with pytest.raises(ValueError, match="cover the whole surface"):
        plan_placement(
            g, surface, 5, D_MM, keep_out=(KeepOut(0.0, 180.0, -50.0, 50.0), KeepOut(180.0, 0.0, -50.0, 50.0))
        )
    with pytest.raises(ValueError, match="cover the whole surface"):
        plan_placement(g, surface, 5, D_MM, keep_out=(KeepOut.parse("0:360,-50:50"),))


def test_keep_out_angles_are_polar_angles_on_an_elliptic_object_too() -> None:
    """On experiment C's torso (semi-axes 120 and 90 mm) the ellipse's parameter angle, which addresses the surface,
    is up to 8 degrees off the polar angle a person measures: the patches and the BBs' angles are polar angles."""
    g = sawtooth(60, 256)
    surface = EllipticCylinder(120.0, 90.0, -70.0, 70.0)
    zone = KeepOut(30.0, 60.0, -70.0, 70.0)
    placed = plan_placement(g, surface, 8, D_MM, keep_out=(zone,), trials=60, rounds=2, min_spacing_mm=20.0, seed=3)
    xyz = surface.points(placed.angle_rad, placed.z_mm, 0.0)
    polar = np.arctan2(xyz[:, 1], xyz[:, 0])
    assert not zone.contains(polar, placed.z_mm).any(), np.degrees(polar) % 360
    # the parameter angle 62 deg lies at the polar angle 54.7 deg: in the patch (it was taken as outside it)
    assert np.degrees(polar_angle(surface, np.radians([62.0]), np.zeros(1)))[0] == pytest.approx(54.7, abs=0.1)
    from calib.plan import _allowed

    assert _allowed(surface, np.radians([62.0, 70.0]), np.zeros(2), (zone,)).tolist() == [False, True]
    turn = np.radians(np.arange(0.0, 360.0, 7.5))
    assert np.allclose(polar_angle(surface, address_angle(surface, turn, 0.0), np.zeros(turn.size)), turn, atol=1e-3)


def test_the_suggested_count_is_the_fewest_bbs_that_reach_the_target() -> None:
    g = sawtooth(60, 256)
    surface = EllipticCylinder(60.0, 60.0, -40.0, 40.0)
    options = {"trials": 30, "rounds": 1, "min_spacing_mm": 15.0}
    loose = suggest_bb_count(g, surface, D_MM, 10.0, n_max=8, **options)
    assert loose.n_bbs is not None and list(loose.tried) == list(range(4, loose.n_bbs + 1))
    reached = loose.tried[loose.n_bbs]
    assert reached["under_determined"] == 0 and reached["predicted_px_max"] <= 10.0
    target = 0.8 * reached["predicted_px_max"]  # a bit better than that count reached: more BBs, or none
    tighter = suggest_bb_count(g, surface, D_MM, target, n_max=12, **options)
    assert tighter.n_bbs is None or tighter.n_bbs > loose.n_bbs
    assert suggest_bb_count(g, surface, D_MM, 1e-6, n_max=6, **options).n_bbs is None


def test_the_search_reports_how_far_it_got() -> None:
    g = sawtooth(60, 256)
    surface = EllipticCylinder(60.0, 60.0, -40.0, 40.0)
    events: list[ProgressEvent] = []
    suggest_bb_count(g, surface, D_MM, 1e-6, n_max=5, trials=30, rounds=1, min_spacing_mm=15.0, progress=events.append)
    counts = [(e.done, e.total) for e in events if e.stage == "count"]
    assert counts == [(0, 2), (1, 2), (1, 2), (2, 2)], counts  # before and after 4 BBs, then 5
    plan = [e for e in events if e.stage == "plan"]
    assert plan[-1].done == plan[-1].total == 30 + 1 * 5 and plan[-1].message == "5 BBs: predicted on every view"
    for n in (4, 5):  # each count's search counts up to its end
        done = [e.done for e in plan if e.message.startswith(f"{n} BBs")]
        assert done == sorted(done) and done[-1] == 30 + n, done


def test_the_search_beats_hand_spirals_and_ends_when_a_round_no_longer_pays() -> None:
    """Moves near each BB's place beside moves anywhere: the plan scores 15 % below every hand spiral of as many BBs,
    and of 40 rounds allowed the search uses only those that still lower its score by 0.5 % (7 here)."""
    g = sawtooth(60, 256)
    surface = EllipticCylinder(60.0, 60.0, -40.0, 40.0)
    events: list[ProgressEvent] = []
    placed = plan_placement(g, surface, 6, D_MM, trials=30, rounds=40, min_spacing_mm=15.0, progress=events.append)
    moves = {e.done for e in events if e.stage == "plan" and "moving BB" in e.message}
    assert 6 <= len(moves) < 40 * 6, len(moves)  # at least one round, far from all of them
    spirals = [
        placement_score(predict_placement(g, hand_spiral(surface, 6, D_MM, seed=s), D_MM, surface=surface))
        for s in range(3)
    ]
    assert placed.score < 0.85 * min(spirals), (placed.score, spirals)


def test_a_bb_at_the_objects_silhouette_is_counted_noisier_across_the_edge() -> None:
    """On a cylinder, a BB's detection window holds the silhouette edge where the ray grazes the surface: there
    (and only near there) its noise is EDGE_NOISE_FACTOR times larger across the edge; the prediction rises."""
    from calib.plan import EDGE_NOISE_FACTOR, edge_noise

    g = sawtooth(120, 256)
    surface = EllipticCylinder(70.0, 70.0, -80.0, 80.0)
    xyz = hand_spiral(surface, 8, D_MM, seed=1)
    var = edge_noise(g, xyz, D_MM, surface)
    eig = np.linalg.eigvalsh(var)
    exposed = eig[..., 1] > 1.5
    np.testing.assert_allclose(
        eig[exposed], np.broadcast_to([1.0, EDGE_NOISE_FACTOR**2], eig[exposed].shape), rtol=1e-9
    )
    np.testing.assert_allclose(eig[~exposed], 1.0)
    ray = xyz[None] - g.S[:, None]
    ray /= np.linalg.norm(ray, axis=-1, keepdims=True)
    normal = xyz[:, :2] / np.linalg.norm(xyz[:, :2], axis=1, keepdims=True)
    graze = np.abs(np.einsum("pka,ka->pk", ray[..., :2], normal))  # 0: the ray grazes the surface at the BB
    assert exposed[graze < 0.1].all() and not exposed[graze > 0.6].any()
    assert 0.1 < exposed.mean() < 0.4
    across = np.linalg.eigh(var[exposed])[1][..., :, 1]
    assert (np.abs(across[:, 0]) > 0.9).all()  # across a z-aligned edge: along the detector's columns
    plain, edgy = predict_placement(g, xyz, D_MM), predict_placement(g, xyz, D_MM, surface=surface)
    assert (edgy.predicted_px >= plain.predicted_px * (1 - 1e-9)).all()
    assert np.nanmedian(edgy.predicted_px) > 1.1 * np.nanmedian(plain.predicted_px)


def test_sixteen_bbs_25_mm_apart_are_placed_on_a_small_cylinder_whatever_the_seed() -> None:
    """Experiment B's count on B's surface: each random start places its BBs one at a time (drawing all 16 at once
    and keeping only spaced sets almost never succeeded; seeds 1 and 2 found none in 200 tries)."""
    g = sawtooth(30, 256)
    surface = EllipticCylinder(61.6, 61.6, -55.0, 55.0)
    for seed in range(3):
        placed = plan_placement(g, surface, 16, D_MM, seed=seed, trials=3, rounds=0)
        d = np.linalg.norm(placed.xyz[:, None] - placed.xyz[None], axis=-1)
        assert d[np.triu_indices(16, 1)].min() >= 25.0
