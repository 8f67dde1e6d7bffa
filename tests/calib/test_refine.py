"""Second passes over a calibration: what they keep when they cannot estimate again."""

from __future__ import annotations

from typing import Any

import numpy as np

from calib import refine
from calib.errors import NoMarkersError
from calib.options import CalibrationOptions
from calib.quality import CalibrationVerdict
from tests.calib.test_identify import _tracks


def test_a_constellation_identified_twice_that_cannot_be_merged_leaves_the_split_result_failed(monkeypatch) -> None:
    """Eight BBs identified again, moved by a similarity, in the second part of the orbit: merged, the pairs leave
    too few BBs to estimate anything. The split result stands and fails, saying why (this branch once raised a
    TypeError of its own: the verdict's ``passed`` is derived from its reasons)."""
    rng = np.random.default_rng(4)
    xyz = rng.uniform(-80.0, 80.0, (8, 3))
    twin = 0.97 * xyz + [9.0, -14.0, 10.0]
    uv = _tracks(200, [range(120)] * 8 + [range(120, 200)] * 8)

    def no_markers(*args: Any, **kw: Any) -> Any:
        raise NoMarkersError("too few BBs")

    monkeypatch.setattr(refine, "estimate", no_markers)
    outcome = (None, np.concatenate([xyz, twin]), None, uv)
    kept, verdict, merged = refine.merge_twins(None, outcome, CalibrationVerdict(), None, CalibrationOptions(), None)  # type: ignore[arg-type]
    assert kept is outcome and merged == 0
    assert not verdict.passed and verdict.status == "failed"
    assert "identified twice" in verdict.reasons[0]
