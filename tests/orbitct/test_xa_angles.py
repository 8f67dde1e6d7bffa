"""A classic XA run's per-frame angles, whichever way its writer stored the angle increments: the three vendor
conventions (offsets from the first frame, steps from the previous frame, absolute angles) and DICOM's single
average, each written into a real XA object with pydicom and imported to the same geometry; a DYNAMIC run whose
views stand still is refused; a reading the values cannot tell apart is left to the user."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pydicom
import pytest
from click.testing import CliRunner

from orbitct.geometry import Panel, ViewGeometry
from orbitct.scanfile import ScanFile, ScanFileError, ScanWriter
from orbitct.scanfile._xa_angles import AngleReadingError, frame_angles, roughness
from orbitct.scanfile.xa import import_xa, write_xa_run

N = 60
START_DEG = -60.0  # a rotational run: the primary angle steps 2 degrees a frame from RAO 60, the tilt stays at CRAN 5


def _true_angles(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)  # encoder read-backs, not perfect steps
    primary = START_DEG + 2.0 * np.arange(N) + np.r_[0.0, rng.normal(0.0, 0.02, N - 1)]
    secondary = 5.0 + np.r_[0.0, rng.normal(0.0, 0.01, N - 1)]
    return primary, secondary


@pytest.fixture(scope="module")
def rotational_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A classic XA run (orbitct's export: increments as offsets) of a C-arm turning 118 degrees in 60 frames."""
    folder = tmp_path_factory.mktemp("rotational")
    primary, secondary = _true_angles()
    panel = Panel(32, 32, 1.0, 1.0)
    geometry = ViewGeometry.from_carm(np.radians(primary), np.radians(secondary), 785.0, 1200.0, panel)
    axes = {"carm.primary": "deg", "carm.secondary": "deg"}
    with ScanWriter(folder / "run.h5", panel, axes=axes, orbit_name="rotational", orbit_params={}) as w:
        for i in range(N):
            angles = {"carm.primary": float(primary[i]), "carm.secondary": float(secondary[i])}
            frame = np.full((32, 32), 1000 + i, np.uint16)
            w.append(frame, "projection", 0.033 * i, nominal_vector=geometry.vectors[i], encoders=angles)
    return write_xa_run(folder / "run.h5", folder / "run.dcm")


def _rewritten(run: Path, out: Path, change: Callable[[pydicom.Dataset], None]) -> Path:
    ds = pydicom.dcmread(run)
    change(ds)
    ds.save_as(out, enforce_file_format=True)
    return out


def _steps(ds: pydicom.Dataset, first: float = 0.0) -> None:
    """A vendor's steps: each frame's change from the previous frame (the first frame's step given as ``first``)."""
    for axis in ("Primary", "Secondary"):
        offsets = np.asarray(ds[f"Positioner{axis}AngleIncrement"].value, dtype=float)
        ds[f"Positioner{axis}AngleIncrement"].value = [f"{v:.6g}" for v in np.r_[first, np.diff(offsets)]]


def _absolute(ds: pydicom.Dataset, keep_start: bool) -> None:
    """Absolute angles in the increments, beside the first-frame angles (a vendor) or zeros (DICOM's note)."""
    for axis in ("Primary", "Secondary"):
        start = float(ds[f"Positioner{axis}Angle"].value)
        offsets = np.asarray(ds[f"Positioner{axis}AngleIncrement"].value, dtype=float)
        ds[f"Positioner{axis}AngleIncrement"].value = [f"{v:.6g}" for v in start + offsets]
        if not keep_start:
            ds[f"Positioner{axis}Angle"].value = "0"


CONVENTIONS = {
    "offsets": (lambda ds: None, "offsets"),
    "steps, the first step 0": (_steps, "steps"),
    "steps, the first step 2": (lambda ds: _steps(ds, first=2.0), "steps"),
    "absolute beside the first-frame angle": (lambda ds: _absolute(ds, keep_start=True), "absolute"),
    "absolute beside zeros (DICOM's note)": (lambda ds: _absolute(ds, keep_start=False), "absolute"),
}


@pytest.mark.parametrize("convention", CONVENTIONS)
def test_each_vendor_convention_imports_with_the_right_geometry(
    rotational_run: Path, tmp_path: Path, convention: str
) -> None:
    change, reading = CONVENTIONS[convention]
    run = _rewritten(rotational_run, tmp_path / "vendor.dcm", change)
    out = import_xa([run], tmp_path / "vendor.h5")
    primary, secondary = _true_angles()
    with ScanFile(out) as sf:
        read = sf.axes("encoders")
        np.testing.assert_allclose(read["carm.primary"][sf.projection_indices], primary, atol=1e-4)
        np.testing.assert_allclose(read["carm.secondary"][sf.projection_indices], secondary, atol=1e-4)
        assumed = sf.attrs_json("provenance", "import_assumptions_json")["assumed"]
    said = [line for line in assumed if "AngleIncrement" in line]
    assert len(said) == 1 and f"read as {reading}" in said[0].replace("read as changes", "read as steps"), said
    assert "vendor.dcm" in said[0] and "2 deg per frame" in said[0]


def test_the_explicit_choice_wins_and_a_wrong_one_is_refused_with_the_reason(
    rotational_run: Path, tmp_path: Path
) -> None:
    run = _rewritten(rotational_run, tmp_path / "steps.dcm", _steps)
    out = import_xa([run], tmp_path / "chosen.h5", angle_increments="steps")
    with ScanFile(out) as sf:
        assert np.ptp(sf.axes("encoders")["carm.primary"][sf.projection_indices]) == pytest.approx(118.0, abs=0.1)
    first_two = _rewritten(rotational_run, tmp_path / "steps2.dcm", lambda ds: _steps(ds, first=2.0))
    with pytest.raises(ScanFileError, match=r"the first frame's angles \(-58.*are not offsets; try auto"):
        import_xa([first_two], tmp_path / "wrong.h5", angle_increments="offsets")


def test_the_issue_run_read_as_offsets_is_refused_not_imported_as_identical_views(
    rotational_run: Path, tmp_path: Path
) -> None:
    """Steps of 2 degrees read as offsets put 59 of 60 views at one angle: a DYNAMIC run that does not move."""
    run = _rewritten(rotational_run, tmp_path / "steps.dcm", _steps)
    with pytest.raises(
        ScanFileError,
        match=r"PositionerMotion is DYNAMIC but 59 of its 60 frames stand within 0.5 deg .*--angle-increments",
    ):
        import_xa([run], tmp_path / "x.h5", angle_increments="offsets")


@pytest.mark.parametrize("increments", ["zeros", "absent"])
def test_a_dynamic_run_whose_views_do_not_move_is_refused(
    rotational_run: Path, tmp_path: Path, increments: str
) -> None:
    def stand(ds: pydicom.Dataset) -> None:
        for axis in ("Primary", "Secondary"):
            if increments == "zeros":
                ds[f"Positioner{axis}AngleIncrement"].value = ["0"] * N
            else:
                del ds[f"Positioner{axis}AngleIncrement"]

    with pytest.raises(ScanFileError, match="PositionerMotion is DYNAMIC but 60 of its 60 frames stand"):
        import_xa([_rewritten(rotational_run, tmp_path / "static.dcm", stand)], tmp_path / "x.h5")
    static = _rewritten(
        rotational_run, tmp_path / "still.dcm", lambda ds: (stand(ds), setattr(ds, "PositionerMotion", "STATIC"))
    )
    with ScanFile(import_xa([static], tmp_path / "still.h5")) as sf:  # a STATIC run of one view, as it says
        assert np.ptp(sf.axes("encoders")["carm.primary"][sf.projection_indices]) == 0.0


def test_one_value_is_the_average_change_per_frame(rotational_run: Path, tmp_path: Path) -> None:
    def average(ds: pydicom.Dataset) -> None:
        ds.PositionerPrimaryAngleIncrement, ds.PositionerSecondaryAngleIncrement = "2", "0"

    with ScanFile(import_xa([_rewritten(rotational_run, tmp_path / "avg.dcm", average)], tmp_path / "a.h5")) as sf:
        np.testing.assert_allclose(
            sf.axes("encoders")["carm.primary"][sf.projection_indices], START_DEG + 2.0 * np.arange(N), atol=1e-9
        )
        assert any(
            "average change per frame" in x for x in sf.attrs_json("provenance", "import_assumptions_json")["assumed"]
        )


def test_the_command_takes_the_choice_and_prints_what_it_read(rotational_run: Path, tmp_path: Path) -> None:
    from orbitct_app.cli.main import cli

    run = _rewritten(rotational_run, tmp_path / "steps.dcm", _steps)
    res = CliRunner().invoke(cli, ["import", "dicom", str(run), "--out", str(tmp_path / "a.h5")])
    assert res.exit_code == 0 and "read as changes from the previous frame (steps)" in res.output, res.output
    res = CliRunner().invoke(
        cli, ["import", "dicom", str(run), "--out", str(tmp_path / "b.h5"), "--angle-increments", "offsets"]
    )
    assert res.exit_code != 0 and "PositionerMotion is DYNAMIC" in res.output and "Traceback" not in res.output
    res = CliRunner().invoke(
        cli, ["import", "dicom", str(run), "--out", str(tmp_path / "c.h5"), "--angle-increments", "x"]
    )
    assert res.exit_code != 0 and "'auto', 'offsets', 'steps', 'absolute'" in res.output


def test_readings_the_values_cannot_tell_apart_are_left_to_the_user() -> None:
    """The evenly moving reading wins; two readings that move about as evenly are refused, naming both."""
    values = np.array([0.0, 1.0, 1.0])  # offsets: a jump then a stop; steps: 1 degree a frame, evenly
    chosen = frame_angles((0.0, 0.0), (values, np.zeros(3)), 3, "auto")
    assert chosen.reading == "steps" and "as offsets the C-arm would move unevenly" in chosen.why
    doubling = np.array([0.0, 1.0, 3.0, 7.0, 15.0])  # the speed doubles each frame as offsets, nearly so as steps
    with pytest.raises(AngleReadingError, match=r"fit two readings .* offsets .*\(steps\); choose one"):
        frame_angles((0.0, 0.0), (doubling, np.zeros(5)), 5, "auto")
    speeding = np.array([0.0, 1.0, 2.1, 3.3, 4.6])  # offsets speeding up by 0.1 a frame, steps by 1: offsets
    assert frame_angles((0.0, 0.0), (speeding, np.zeros(5)), 5, "auto").reading == "offsets"
    assert roughness(np.zeros((5, 2))) == float("inf")
