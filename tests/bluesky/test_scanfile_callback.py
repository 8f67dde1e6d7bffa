"""A scan recorded through bluesky's documents becomes an orbitct scan file that calibrates as the original does."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import event_model
import numpy as np
import pytest
from click.testing import CliRunner

import calib
from orbitct.scanfile import ImageKey, ScanFile
from orbitct_app.cli.main import cli
from orbitct_bluesky import ScanFileCallback, orbitct_metadata

AXES = {
    "orbit.rotation": ("deg", "orbit_rotation", "orbit_rotation_set"),
    "orbit.tilt": ("deg", "orbit_tilt", "orbit_tilt_set"),
}


def run_documents(scan: Path, *, stop_after: int | None = None) -> Iterator[tuple[str, dict[str, Any]]]:
    """The documents a bluesky run of ``scan``'s frames emits (validated by event-model as they are made):
    start, one descriptor, an event per frame, stop (aborted after ``stop_after`` frames when given)."""
    with ScanFile(scan) as sf:
        name, params = sf.orbit
        diameter = sf.marker_diameter_mm
        md = orbitct_metadata(sf.panel, AXES, orbit_name=name, orbit_params=params, marker_diameter_mm=diameter)
        run = event_model.compose_run(metadata={"orbitct": md, "plan_name": "orbit_scan", "num_points": sf.n_frames})
        yield "start", run.start_doc
        rows, cols = sf.panel.shape
        keys = {
            "image": {"source": "panel", "dtype": "array", "shape": [rows, cols]},
            "image_key": {"source": "panel", "dtype": "integer", "shape": []},
            "nominal_vector": {"source": "orbit", "dtype": "array", "shape": [12]},
        }
        for _, readback, commanded in AXES.values():
            keys[readback] = {"source": "axis", "dtype": "number", "shape": []}
            keys[commanded] = {"source": "axis", "dtype": "number", "shape": []}
        stream = run.compose_descriptor(name="primary", data_keys=keys)
        yield "descriptor", stream.descriptor_doc
        encoders, commanded_at = sf.axes("encoders"), sf.axes("commanded")
        vectors = sf.geometry("nominal").vectors
        n = sf.n_frames if stop_after is None else stop_after
        for i in range(n):
            key = int(sf.image_key[i])
            data: dict[str, Any] = {
                "image": np.asarray(sf.frames[i]),
                "image_key": key,
                "nominal_vector": (vectors[i] if key == ImageKey.PROJECTION else np.full(12, np.nan)).tolist(),
            }
            for axis, (_, readback, commanded) in AXES.items():
                data[readback], data[commanded] = float(encoders[axis][i]), float(commanded_at[axis][i])
            now = run.start_doc["time"] + float(sf.time_s[i])
            yield "event", stream.compose_event(data=data, timestamps=dict.fromkeys(data, now), time=now)
        if stop_after is None:
            yield "stop", run.compose_stop(exit_status="success")
        else:
            yield "stop", run.compose_stop(exit_status="abort", reason="aborted by the operator")


@pytest.fixture(scope="module")
def original(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from orbitct.errorprofiles import make_profile
    from orbitct.simulator.scan import simulate_scan

    path = tmp_path_factory.mktemp("bluesky") / "original.h5"
    simulate_scan("A", out=path, n_frames=120, detector_px=192, errors=make_profile("bench", 0, angle_scale=0.24))
    return path


def record(documents: Iterator[tuple[str, dict[str, Any]]], out: Path) -> Path:
    callback = ScanFileCallback(out)
    for name, doc in documents:
        callback(name, doc)
    return out


def test_a_run_written_from_its_documents_calibrates_as_the_original(original: Path, tmp_path: Path) -> None:
    recorded = record(run_documents(original), tmp_path / "bluesky.h5")
    with ScanFile(original) as a, ScanFile(recorded) as b:
        assert b.status == "complete" and b.n_frames == a.n_frames
        np.testing.assert_array_equal(b.image_key, a.image_key)
        np.testing.assert_array_equal(np.asarray(b.frames[:]), np.asarray(a.frames[:]))
        proj = a.projection_indices
        np.testing.assert_array_equal(b.geometry("nominal").vectors[proj], a.geometry("nominal").vectors[proj])
        for axis in AXES:
            np.testing.assert_array_equal(b.axes("encoders")[axis], a.axes("encoders")[axis])
        assert b.orbit == a.orbit and b.marker_diameter_mm == a.marker_diameter_mm
    r = CliRunner().invoke(cli, ["inspect", str(recorded)])
    assert r.exit_code == 0, r.output
    first = calib.calibrate_scan(original, out=tmp_path / "first.h5")
    again = calib.calibrate_scan(recorded, out=tmp_path / "again.h5")
    assert again.quality is not None and again.quality.passed, again.quality
    assert again.n_bbs == first.n_bbs
    np.testing.assert_allclose(again.geometry.vectors[proj], first.geometry.vectors[proj], rtol=0, atol=1e-6)


def test_events_sent_as_pages_are_written_alike(original: Path, tmp_path: Path) -> None:
    """A run may send its events in pages (several events in one document): the file is the same."""
    documents = list(run_documents(original, stop_after=30))
    events = [doc for name, doc in documents if name == "event"]
    paged = [d for d in documents if d[0] != "event"]
    paged[2:2] = [("event_page", event_model.pack_event_page(*events[i : i + 8])) for i in range(0, 30, 8)]
    one, other = record(iter(documents), tmp_path / "events.h5"), record(iter(paged), tmp_path / "pages.h5")
    with ScanFile(one) as a, ScanFile(other) as b:
        assert b.n_frames == a.n_frames == 30
        np.testing.assert_array_equal(np.asarray(b.frames[:]), np.asarray(a.frames[:]))
        np.testing.assert_array_equal(b.time_s, a.time_s)


def test_an_aborted_run_leaves_the_frames_taken_so_far(original: Path, tmp_path: Path) -> None:
    recorded = record(run_documents(original, stop_after=37), tmp_path / "aborted.h5")
    with ScanFile(recorded) as sf:
        assert sf.status == "aborted" and sf.n_frames == 37
        assert "aborted by the operator" in sf.status_reason
        assert np.asarray(sf.frames[36]).shape == sf.panel.shape


def test_a_run_without_orbitct_metadata_is_refused_before_anything_is_written(tmp_path: Path) -> None:
    run = event_model.compose_run(metadata={"plan_name": "count"})
    callback = ScanFileCallback(tmp_path / "x.h5")
    with pytest.raises(ValueError, match="no 'orbitct' entry"):
        callback("start", run.start_doc)
    assert not (tmp_path / "x.h5").exists()


def test_a_stream_missing_a_named_axis_is_refused(original: Path, tmp_path: Path) -> None:
    documents = run_documents(original)
    callback: Callable[[str, dict[str, Any]], None] = ScanFileCallback(tmp_path / "y.h5")
    name, start = next(documents)
    callback(name, start)
    _, descriptor = next(documents)
    descriptor = {**descriptor, "data_keys": {k: v for k, v in descriptor["data_keys"].items() if k != "orbit_tilt"}}
    with pytest.raises(ValueError, match=r"lacks the data keys \['orbit_tilt'\]"):
        callback("descriptor", descriptor)
