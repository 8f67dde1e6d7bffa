"""``orbitct export dicom``: a stored reconstruction as a CT series; clear errors for what cannot be exported."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pydicom
from click.testing import CliRunner

from orbitct.scanfile import ScanFile
from orbitct_app.cli.main import cli
from tests.helpers.service import write_small_scan


def test_export_dicom_writes_a_series_with_the_provenance_and_refuses_what_it_cannot(tmp_path: Path) -> None:
    scan = write_small_scan(tmp_path / "bench-01.h5")
    volume = np.full((6, 5, 4), 0.0206, np.float32)
    volume[3, 2, 1] = 0.0412
    with ScanFile(scan, "r+") as sf:
        sf.write_recon(
            "fdk_nominal",
            volume,
            voxel_mm=(0.5, 0.5, 2.0),
            origin_mm=(-1.0, -1.0, -5.0),
            algorithm="fdk",
            geometry="nominal",
            iterations=0,
            elapsed_s=0.1,
            params={},
        )
    runner = CliRunner()
    res = runner.invoke(
        cli,
        [
            "export",
            "dicom",
            str(scan),
            "--recon",
            "fdk_nominal",
            "--out",
            str(tmp_path / "ct"),
            "--study-description",
            "phantom A",
        ],
    )
    assert res.exit_code == 0, res.output
    assert "wrote 6 CT slices of 4x5 px" in res.output and "FDK nominal geometry" in res.output
    files = sorted((tmp_path / "ct").glob("CT*.dcm"))
    assert len(files) == 6
    ds = pydicom.dcmread(files[3])
    assert ds.PatientID == "bench-01" and ds.StudyDescription == "phantom A" and "fdk_nominal" in ds.SeriesDescription
    assert int(ds.pixel_array[2, 1]) == 1000 and float(ds.ImagePositionPatient[2]) == 1.0

    res = runner.invoke(
        cli, ["export", "dicom", str(scan), "--recon", "fdk_nominal", "--out", str(tmp_path / "ect"), "--enhanced"]
    )
    assert res.exit_code == 0 and "one Enhanced CT object of 6 frames of 4x5 px" in res.output, res.output
    ds = pydicom.dcmread(tmp_path / "ect" / "CT_ENHANCED.dcm")
    assert ds.SOPClassUID == "1.2.840.10008.5.1.4.1.1.2.1" and ds.pixel_array.shape == (6, 5, 4)
    assert int(ds.pixel_array[3, 2, 1]) == 1000 and "fdk_nominal" in ds.SeriesDescription

    again = runner.invoke(cli, ["export", "dicom", str(scan), "--recon", "fdk_nominal", "--out", str(tmp_path / "ct")])
    assert again.exit_code != 0 and "is not empty" in again.output
    missing = runner.invoke(cli, ["export", "dicom", str(scan), "--recon", "pwls", "--out", str(tmp_path / "x")])
    assert missing.exit_code != 0 and "no reconstruction 'pwls'" in missing.output and "fdk_nominal" in missing.output
    assert "Traceback" not in missing.output


def test_export_nxtomo_writes_the_file_and_refuses_to_overwrite(tmp_path: Path) -> None:
    scan = write_small_scan(tmp_path / "small.h5")
    runner = CliRunner()
    res = runner.invoke(cli, ["export", "nxtomo", str(scan), "--out", str(tmp_path / "small.nx")])
    assert res.exit_code == 0 and "NXtomo entry /entry0000" in res.output, res.output
    again = runner.invoke(cli, ["export", "nxtomo", str(scan), "--out", str(tmp_path / "small.nx")])
    assert again.exit_code != 0 and "exists" in again.output and "Traceback" not in again.output
    assert (
        runner.invoke(
            cli, ["export", "nxtomo", str(scan), "--out", str(tmp_path / "small.nx"), "--overwrite"]
        ).exit_code
        == 0
    )
