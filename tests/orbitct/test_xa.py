"""C-arm runs as DICOM XA: the twin's scan exported as a C-arm exports it, imported back to the same nominal
geometry (one run or several), and every missing or contradictory attribute refused by name."""

from __future__ import annotations

import copy
import subprocess
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pydicom
import pytest

from acquire.config import parse_config
from acquire.runner import ScanRequest, run_scan
from orbitct.scanfile import ScanFile, ScanFileError
from orbitct.scanfile.xa import import_xa, write_xa_run
from tests.helpers.tools import require_tool

pytestmark = [pytest.mark.system, pytest.mark.timeout(180)]


@pytest.fixture(scope="module")
def carm_scan(tmp_path_factory: pytest.TempPathFactory) -> Path:
    cfg = parse_config(
        {
            "kind": "carm",
            "geometry": {"detector": {"rows": 64, "cols": 64}},
            "calibration_frames": {"darks_before": 1, "flats_before": 1, "darks_after": 0, "flats_after": 0},
            "sim": {"time_scale": 25.0},
        }
    )
    out = tmp_path_factory.mktemp("carm") / "carm.h5"
    res = run_scan(
        ScanRequest(
            config=cfg,
            out=out,
            orbit="sawtooth",
            frames=80,
            sim=True,
            orbit_params={"start_deg": -180.0, "amplitude_deg": 10.0},
        )
    )
    assert res.status == "complete", res.reason
    return out


def _valid(path: Path) -> None:
    res = subprocess.run(
        [require_tool("dciodvfy", "dicom3tools"), str(path)], capture_output=True, text=True, timeout=60
    )
    assert not [x for x in (res.stdout + res.stderr).splitlines() if x.startswith("Error")], res.stderr


@pytest.mark.parametrize(
    ("kind", "sop_class", "modality"),
    [
        ("xa", "1.2.840.10008.5.1.4.1.1.12.1", "XA"),
        ("xrf", "1.2.840.10008.5.1.4.1.1.12.2", "RF"),
        ("enhanced-xa", "1.2.840.10008.5.1.4.1.1.12.1.1", "XA"),
    ],
)
def test_the_twins_run_comes_back_from_xa_with_its_nominal_geometry(
    carm_scan: Path, tmp_path: Path, kind: str, sop_class: str, modality: str
) -> None:
    xa = write_xa_run(carm_scan, tmp_path / "run1.dcm", kind=kind)  # type: ignore[arg-type]
    ds = pydicom.dcmread(xa)
    assert ds.SOPClassUID == sop_class and ds.Modality == modality and int(ds.NumberOfFrames) == 80
    _valid(xa)
    if kind == "enhanced-xa":  # the angles per frame in functional groups, the technique from the bench's configuration
        assert "PositionerPrimaryAngle" not in ds and float(ds.KVP) == 90.0
        assert len(ds.PerFrameFunctionalGroupsSequence) == 80
        assert (
            ds.PerFrameFunctionalGroupsSequence[5].PositionerPositionSequence[0].PositionerPrimaryAngle
            != ds.PerFrameFunctionalGroupsSequence[0].PositionerPositionSequence[0].PositionerPrimaryAngle
        )
    else:
        assert ds.PositionerMotion == "DYNAMIC"
    scan = import_xa([xa], tmp_path / "imported.h5")
    with ScanFile(carm_scan) as a, ScanFile(scan) as b:
        proj = a.projection_indices
        assert (
            b.count_by_kind()["projection"] == 80 and b.count_by_kind()["dark"] == 1 and b.count_by_kind()["flat"] == 1
        )
        assert np.array_equal(np.asarray(b.frames[b.projection_indices.tolist()]), np.asarray(a.frames[proj.tolist()]))
        read = a.axes("encoders")
        np.testing.assert_allclose(
            b.axes("encoders")["carm.primary"][b.projection_indices], read["carm.primary"][proj], atol=1e-4
        )
        # the imported nominal geometry is the scan's, up to the encoders' difference from the commanded angles
        gap_deg = np.abs(read["carm.primary"][proj] - a.axes("commanded")["carm.primary"][proj]).max()
        assert b.geometry("nominal")[b.projection_indices].allclose(
            a.geometry("nominal")[proj], atol_mm=1e-3 + 20 * gap_deg
        )
        assumptions = b.attrs_json("provenance", "import_assumptions_json")["assumed"]
        assert any("dark" in x for x in assumptions) and any("principal point" in x for x in assumptions)
        assert any("PixelIntensityRelationship LIN" in x for x in assumptions)


def test_an_orbit_in_several_runs_imports_in_acquisition_order(carm_scan: Path, tmp_path: Path) -> None:
    runs = [write_xa_run(carm_scan, tmp_path / f"run{i}.dcm", part=(27 * i, 27 * (i + 1))) for i in range(3)]
    whole = import_xa([runs[2], runs[0], runs[1]], tmp_path / "three.h5")  # given out of order
    single = import_xa([write_xa_run(carm_scan, tmp_path / "all.dcm")], tmp_path / "one.h5")
    with ScanFile(whole) as a, ScanFile(single) as b:
        assert a.geometry("nominal").allclose(b.geometry("nominal"), atol_mm=1e-6)
        assert a.orbit[1]["runs"] == 3


@pytest.mark.parametrize(
    "attribute",
    [
        "DistanceSourceToDetector",
        "DistanceSourceToPatient",
        "ImagerPixelSpacing",
        "PositionerPrimaryAngle",
        "NumberOfFrames",
    ],
)
def test_a_missing_attribute_is_named(carm_scan: Path, tmp_path: Path, attribute: str) -> None:
    xa = write_xa_run(carm_scan, tmp_path / "run.dcm")
    ds = pydicom.dcmread(xa)
    delattr(ds, attribute)
    ds.save_as(xa)
    with pytest.raises(ScanFileError, match=f"missing {attribute}"):
        import_xa([xa], tmp_path / "x.h5")


def test_contradictory_attributes_are_refused(carm_scan: Path, tmp_path: Path) -> None:
    xa = write_xa_run(carm_scan, tmp_path / "run.dcm")
    ds = pydicom.dcmread(xa)
    ds.PositionerPrimaryAngleIncrement = ds.PositionerPrimaryAngleIncrement[:-1]
    ds.save_as(xa)
    with pytest.raises(ScanFileError, match="PositionerPrimaryAngleIncrement has 79 values for 80 frames"):
        import_xa([xa], tmp_path / "x.h5")
    ds.PositionerPrimaryAngleIncrement = [0] * 80
    ds.DistanceSourceToPatient = 2000
    ds.save_as(xa)
    with pytest.raises(ScanFileError, match="must exceed DistanceSourceToPatient"):
        import_xa([xa], tmp_path / "y.h5")
    other = write_xa_run(carm_scan, tmp_path / "other.dcm")
    ds = pydicom.dcmread(other)
    ds.DistanceSourceToDetector = 1300
    ds.save_as(other)
    with pytest.raises(ScanFileError, match=r"sdd 1[23]00.0 differs from .*1[23]00.0"):
        import_xa([write_xa_run(carm_scan, tmp_path / "a.dcm"), other], tmp_path / "z.h5")
    ct = tmp_path / "ct.dcm"
    ds.Modality = "CT"
    ds.save_as(ct)
    with pytest.raises(ScanFileError, match="expected an XA"):
        import_xa([ct], tmp_path / "w.h5")


def test_runs_of_one_orbit_may_come_as_different_kinds(carm_scan: Path, tmp_path: Path) -> None:
    runs = [
        write_xa_run(carm_scan, tmp_path / f"run{i}.dcm", part=(40 * i, 40 * (i + 1)), kind=kind)  # type: ignore[arg-type]
        for i, kind in enumerate(("enhanced-xa", "xa"))
    ]
    mixed = import_xa(runs, tmp_path / "mixed.h5")
    single = import_xa([write_xa_run(carm_scan, tmp_path / "all.dcm")], tmp_path / "one.h5")
    with ScanFile(mixed) as a, ScanFile(single) as b:
        assert a.geometry("nominal").allclose(b.geometry("nominal"), atol_mm=1e-6)
        assumed = a.attrs_json("provenance", "import_assumptions_json")["assumed"]
        assert any(x.startswith("Enhanced XA:") for x in assumed) and any(
            x.startswith("classic XA/XRF:") for x in assumed
        )


def _edit_enhanced(carm_scan: Path, tmp_path: Path, edit: Callable[[Any], None]) -> Path:
    path = write_xa_run(carm_scan, tmp_path / "enhanced.dcm", kind="enhanced-xa")
    ds = pydicom.dcmread(path)
    edit(ds)
    ds.save_as(path)
    return path


def _frame(ds: Any, i: int) -> Any:
    return ds.PerFrameFunctionalGroupsSequence[i]


def _shared(ds: Any) -> Any:
    return ds.SharedFunctionalGroupsSequence[0]


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda ds: delattr(_frame(ds, 7), "PositionerPositionSequence"), "frame 8 has no PositionerPositionSequence"),
        (
            lambda ds: delattr(_frame(ds, 3).PositionerPositionSequence[0], "PositionerSecondaryAngle"),
            "missing PositionerSecondaryAngle",
        ),
        (lambda ds: delattr(_shared(ds), "XRayGeometrySequence"), "no XRayGeometrySequence"),
        (
            lambda ds: delattr(_shared(ds).XRayGeometrySequence[0], "DistanceSourceToIsocenter"),
            "missing DistanceSourceToIsocenter",
        ),
        (
            lambda ds: delattr(_shared(ds).FramePixelDataPropertiesSequence[0], "ImagerPixelSpacing"),
            "missing ImagerPixelSpacing",
        ),
        (
            lambda ds: setattr(_shared(ds).FramePixelDataPropertiesSequence[0], "PixelIntensityRelationship", "LOG"),
            "PixelIntensityRelationship is LOG; only LIN",
        ),
        (
            lambda ds: (
                setattr(_frame(ds, 9), "XRayGeometrySequence", copy.deepcopy(_shared(ds).XRayGeometrySequence))
                or setattr(_frame(ds, 9).XRayGeometrySequence[0], "DistanceSourceToDetector", 1400.0)
            ),
            "DistanceSourceToDetector changes between frames",
        ),
        (
            lambda ds: setattr(ds, "PerFrameFunctionalGroupsSequence", ds.PerFrameFunctionalGroupsSequence[:-1]),
            "PerFrameFunctionalGroupsSequence has 79 items for 80 frames",
        ),
    ],
)
def test_what_an_enhanced_run_lacks_or_contradicts_is_named(
    carm_scan: Path, tmp_path: Path, edit: Callable[[Any], None], message: str
) -> None:
    with pytest.raises(ScanFileError, match=message):
        import_xa([_edit_enhanced(carm_scan, tmp_path, edit)], tmp_path / "x.h5")


def test_the_commands_export_and_import_a_run(carm_scan: Path, tmp_path: Path) -> None:
    from click.testing import CliRunner

    from orbitct_app.cli.main import cli

    runner = CliRunner()
    res = runner.invoke(
        cli, ["export", "xa", str(carm_scan), "--out", str(tmp_path / "runs" / "r1.dcm"), "--frames", "0:40"]
    )
    assert res.exit_code == 0, res.output
    assert (
        runner.invoke(
            cli, ["export", "xa", str(carm_scan), "--out", str(tmp_path / "runs" / "r2.dcm"), "--frames", "40:80"]
        ).exit_code
        == 0
    )
    assert (
        runner.invoke(
            cli,
            [
                "export",
                "xa",
                str(carm_scan),
                "--out",
                str(tmp_path / "runs" / "r3.dcm"),
                "--frames",
                "80:80",
                "--kind",
                "enhanced-xa",
            ],
        ).exit_code
        != 0
    )  # no frames
    res = runner.invoke(cli, ["import", "dicom", str(tmp_path / "runs"), "--out", str(tmp_path / "in.h5")])
    assert (
        res.exit_code == 0 and "80 projections from 2 run(s)" in res.output and "assumed: principal point" in res.output
    )
    with ScanFile(tmp_path / "in.h5", "r+") as sf:  # a volume of the imported run goes out with the caveat
        sf.write_recon(
            "fdk",
            np.zeros((2, 3, 4), np.float32),
            voxel_mm=(1.0, 1.0, 1.0),
            origin_mm=(0.0, 0.0, 0.0),
            algorithm="fdk",
            geometry="nominal",
            iterations=0,
            elapsed_s=0.1,
            params={},
        )
    res = runner.invoke(
        cli, ["export", "dicom", str(tmp_path / "in.h5"), "--recon", "fdk", "--out", str(tmp_path / "ct")]
    )
    assert res.exit_code == 0 and "warning: reconstructed from an imported C-arm run: left and right" in res.output
    assert "mirror image" in pydicom.dcmread(tmp_path / "ct" / "CT000001.dcm").ImageComments
    res = runner.invoke(
        cli, ["export", "xa", str(carm_scan), "--out", str(tmp_path / "enh" / "r.dcm"), "--kind", "enhanced-xa"]
    )
    assert res.exit_code == 0 and "(enhanced-xa)" in res.output, res.output
    assert pydicom.dcmread(tmp_path / "enh" / "r.dcm").SOPClassUID == "1.2.840.10008.5.1.4.1.1.12.1.1"
    res = runner.invoke(cli, ["export", "xa", str(carm_scan), "--out", str(tmp_path / "k.dcm"), "--kind", "ct"])
    assert res.exit_code != 0 and "xa" in res.output and "enhanced-xa" in res.output
    bad = runner.invoke(cli, ["export", "xa", str(carm_scan), "--out", str(tmp_path / "x.dcm"), "--frames", "a:b"])
    assert bad.exit_code != 0 and "FIRST:LAST" in bad.output
    none = runner.invoke(cli, ["import", "dicom", str(tmp_path), "--out", str(tmp_path / "n.h5")])
    assert none.exit_code != 0 and "no .dcm files" in none.output and "Traceback" not in none.output
