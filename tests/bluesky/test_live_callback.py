"""Live calibration as a callback on the orbit plan's documents: the geometry in the file when the run ends is
the offline calibration's."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import event_model
import pytest
from bluesky import RunEngine

from acquire.config import BenchConfig
from orbitct_bluesky import Bench, LiveCalibrationCallback, ScanFileCallback, orbit_plan
from tests.bluesky.test_orbit_plan import SAWTOOTH
from tests.helpers.bench import small_config
from tests.helpers.calib_scans import assert_live_geometry_is_offline


@pytest.mark.slow
def test_a_run_calibrated_live_has_the_offline_geometry_when_it_ends(
    RE: RunEngine, open_bench: Callable[[BenchConfig], Bench], tmp_path: Path
) -> None:
    """Darks and flats only before the projections: live detection normalises exactly as offline does."""
    cfg = small_config(
        size=192, calibration_frames={"darks_before": 2, "flats_before": 2, "darks_after": 0, "flats_after": 0}
    )
    bench = open_bench(cfg)
    out = tmp_path / "live.h5"
    warnings: list[str] = []
    RE.subscribe(ScanFileCallback(out))  # first: the file is closed before the final solve reads it
    live = LiveCalibrationCallback(out, cfg.sim.bb_diameter_mm, on_warning=lambda w: warnings.append(w.message))
    RE.subscribe(live)
    RE(orbit_plan(bench, SAWTOOTH))
    assert live.error is None and live.result is not None
    assert_live_geometry_is_offline(out, tmp_path)


def test_a_run_without_its_frames_is_refused_with_a_sentence(tmp_path: Path) -> None:
    run = event_model.compose_run(metadata={"plan_name": "count"})
    with pytest.raises(ValueError, match="needs the run's frames"):
        LiveCalibrationCallback(tmp_path / "x.h5", 3.17)("start", run.start_doc)
