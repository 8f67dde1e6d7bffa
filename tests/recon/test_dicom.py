"""Reconstructions as DICOM CT series: geometry in patient coordinates, Hounsfield units, valid objects (dciodvfy)."""

from __future__ import annotations

import subprocess
from pathlib import Path

import numpy as np
import pydicom
import pytest

from orbitct.geometry import VolumeGrid
from recon.dicom import SeriesInfo, export_dicom_ct, export_enhanced_ct, to_hounsfield
from recon.errors import ReconError
from tests.helpers.tools import require_tool


def _sphere() -> tuple[VolumeGrid, np.ndarray, np.ndarray]:
    grid = VolumeGrid((20, 24, 28), (0.8, 0.8, 1.25), (-10.8, -9.2, -12.5))  # anisotropic, off-centre, nx != ny
    z, y, x = np.meshgrid(*(np.arange(n) for n in grid.shape), indexing="ij")
    pos = np.stack(
        [
            grid.origin_mm[0] + x * grid.voxel_mm[0],
            grid.origin_mm[1] + y * grid.voxel_mm[1],
            grid.origin_mm[2] + z * grid.voxel_mm[2],
        ],
        axis=-1,
    )
    centre = np.array([3.1, -4.0, 6.2])  # a bone-like sphere off the axes, in the object frame (mm)
    volume = np.full(grid.shape, 0.0206, np.float32)
    volume[np.linalg.norm(pos - centre, axis=-1) < 2.5] = 0.06
    return grid, volume, centre


def _series(tmp_path: Path) -> tuple[VolumeGrid, np.ndarray, np.ndarray, list[Path]]:
    grid, volume, centre = _sphere()
    files = export_dicom_ct(volume, grid, tmp_path / "series", SeriesInfo(description="test", patient_id="P1"))
    return grid, volume, centre, files


def _bright_centre(images: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]) -> np.ndarray:
    """HU-weighted centre (patient mm) of voxels above 500 HU; each image as (hu, position, orientation, spacing)."""
    points, weights = [], []
    for hu, ipp, iop, spacing in images:
        row_dir, col_dir = iop[:3], iop[3:]
        dr, dc = spacing
        for r, c in zip(*np.nonzero(hu > 500)):
            points.append(ipp + c * dc * row_dir + r * dr * col_dir)  # column index along the row direction
            weights.append(hu[r, c])
    return np.average(np.array(points), axis=0, weights=weights)


def test_the_series_puts_a_known_sphere_where_the_object_frame_has_it(tmp_path: Path) -> None:
    grid, volume, centre, files = _series(tmp_path)
    slices = [pydicom.dcmread(f) for f in files]
    assert len(slices) == grid.shape[0] and len({s.SeriesInstanceUID for s in slices}) == 1
    assert len({s.SOPInstanceUID for s in slices}) == len(slices) and slices[0].Modality == "CT"
    images = [
        (
            s.pixel_array.astype(float) * float(s.RescaleSlope) + float(s.RescaleIntercept),
            np.array(s.ImagePositionPatient, float),
            np.array(s.ImageOrientationPatient, float),
            [float(v) for v in s.PixelSpacing],
        )
        for s in slices
    ]
    assert images[0][0].shape == (grid.shape[1], grid.shape[2])
    found = _bright_centre(images)
    assert np.all(np.abs(found - centre) < 0.5 * np.array(grid.voxel_mm)), (found, centre)
    water = slices[0].pixel_array.astype(float) * float(slices[0].RescaleSlope) + float(slices[0].RescaleIntercept)
    assert np.all(water == 0)  # water is 0 HU
    assert float(slices[0].SliceThickness) == pytest.approx(1.25) and float(
        slices[1].ImagePositionPatient[2]
    ) == pytest.approx(-11.25)


def test_hounsfield_units_are_clipped_and_bad_input_is_refused(tmp_path: Path) -> None:
    hu = to_hounsfield(np.array([0.0, 0.0206, 0.0412, 10.0, np.nan]), 0.0206)
    assert hu.tolist() == [-1000, 0, 1000, 32767, -1024]
    with pytest.raises(ReconError, match="water attenuation"):
        to_hounsfield(np.zeros(3), 0.0)
    with pytest.raises(ReconError, match="does not match the grid"):
        export_dicom_ct(np.zeros((2, 3, 4), np.float32), VolumeGrid((2, 3, 5), 1.0, (0, 0, 0)), tmp_path)


def test_every_object_passes_dciodvfy(tmp_path: Path) -> None:
    tool = require_tool("dciodvfy", "dicom3tools")
    _, _, _, files = _series(tmp_path)
    for f in (files[0], files[len(files) // 2], files[-1]):
        res = subprocess.run([tool, str(f)], capture_output=True, text=True, timeout=60)
        errors = [line for line in (res.stdout + res.stderr).splitlines() if line.startswith("Error")]
        assert not errors, f"{f.name}: {errors}"


def test_one_enhanced_ct_object_holds_the_same_volume_in_the_same_place(tmp_path: Path) -> None:
    grid, volume, centre = _sphere()
    path = export_enhanced_ct(volume, grid, tmp_path / "ct.dcm", SeriesInfo(description="test", patient_id="P1"))
    res = subprocess.run(
        [require_tool("dciodvfy", "dicom3tools"), str(path)], capture_output=True, text=True, timeout=60
    )
    assert not [x for x in (res.stdout + res.stderr).splitlines() if x.startswith("Error")], res.stderr
    ds = pydicom.dcmread(path)
    assert ds.SOPClassUID == "1.2.840.10008.5.1.4.1.1.2.1" and int(ds.NumberOfFrames) == grid.shape[0]
    shared = ds.SharedFunctionalGroupsSequence[0]
    rescale = shared.PixelValueTransformationSequence[0]
    iop = np.array(shared.PlaneOrientationSequence[0].ImageOrientationPatient, float)
    spacing = [float(v) for v in shared.PixelMeasuresSequence[0].PixelSpacing]
    hu = ds.pixel_array.astype(float) * float(rescale.RescaleSlope) + float(rescale.RescaleIntercept)
    images = [
        (hu[k], np.array(f.PlanePositionSequence[0].ImagePositionPatient, float), iop, spacing)
        for k, f in enumerate(ds.PerFrameFunctionalGroupsSequence)
    ]
    found = _bright_centre(images)
    assert np.all(np.abs(found - centre) < 0.5 * np.array(grid.voxel_mm)), (found, centre)
    np.testing.assert_array_equal(hu, to_hounsfield(volume, 0.0206))  # the series' values, frame k = slice k
