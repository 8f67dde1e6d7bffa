"""The verdict every result carries: three states, one sentence, stored and read back through HDF5 attributes."""

from __future__ import annotations

from pathlib import Path

import h5py

from orbitct.verdict import Verdict


def test_reasons_fail_warnings_pass_with_warnings_and_nothing_passes() -> None:
    assert Verdict().status == "passed" and Verdict().sentence() == "passed"
    warned = Verdict(warnings=("2 views bridged",))
    assert warned.passed and warned.status == "passed_with_warnings"
    assert warned.sentence() == "passed with warnings: 2 views bridged"
    failed = Verdict(reasons=("3 views failed", "noise unknown"), warnings=("2 views bridged",))
    assert not failed.passed and failed.status == "failed"
    assert failed.sentence() == "failed: 3 views failed; noise unknown"
    assert failed.summary() == {
        "status": "failed",
        "label": "failed",
        "reasons": ["3 views failed", "noise unknown"],
        "warnings": ["2 views bridged"],
    }


def test_a_verdict_round_trips_through_a_groups_attributes(tmp_path: Path) -> None:
    verdict = Verdict(reasons=("frame 7: ünïcode reason",), warnings=("a warning",))
    with h5py.File(tmp_path / "v.h5", "w") as f:
        f.create_group("old")  # written before verdicts existed
        f.create_group("new").attrs.update(verdict.attrs())
        f.create_group("bare").attrs["verdict"] = "failed"  # a failure must keep a reason
    with h5py.File(tmp_path / "v.h5") as f:
        assert Verdict.from_attrs(f["old"].attrs) is None
        assert Verdict.from_attrs(f["new"].attrs) == verdict
        bare = Verdict.from_attrs(f["bare"].attrs)
    assert bare is not None and bare.status == "failed" and bare.reasons
