"""End-to-end: a tiny simulated scan reads back with its truth."""

from pathlib import Path

import numpy as np

from orbitct.scanfile import ScanFile
from orbitct.simulator import simulate_scan


def test_tiny_scan_round_trips(tmp_path: Path) -> None:
    res = simulate_scan("A", out=tmp_path / "a.h5", n_frames=6, detector_px=64, n_dark=2, n_flat=2, seed=3)
    with ScanFile(res.path) as f:
        assert f.count_by_kind() == {"projection": 6, "flat": 2, "dark": 2, "invalid": 0}
        assert f.status == "complete"
        assert f.marker_diameter_mm == 3.17
        assert np.allclose(f.truth_markers_xyz(), res.phantom.markers_xyz)
        assert f.geometry("truth")[4:].valid.all() and not f.geometry("truth")[:4].valid.any()
        assert f.orbit[0] == "sawtooth"
