"""Geometry exporters (RTK XML, ASTRA cone_vec) and image quality measures."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from orbitct.geometry import ViewGeometry
from recon import VolumeGrid, wire_fwhm
from recon.export import (
    RTK_FROM_OBJECT,
    astra_geometries,
    read_rtk_geometry,
    rtk_matrix,
    rtk_parameters,
    write_rtk_geometry,
)


def test_rtk_file_reproduces_projection_matrices(random_geometry: ViewGeometry, tmp_path: Path) -> None:
    path = tmp_path / "geometry.xml"
    layout = write_rtk_geometry(random_geometry, path)
    assert path.read_text().count("<Projection>") == random_geometry.n_views
    back = read_rtk_geometry(path, random_geometry.panel)
    assert back.allclose(random_geometry, atol_mm=1e-9)
    det = random_geometry.panel
    pts = np.random.default_rng(0).normal(0, 20, (15, 3))
    uv = random_geometry.project(pts)
    params, _ = rtk_parameters(random_geometry)
    for n, p in enumerate(params):
        h = rtk_matrix(p) @ np.c_[pts @ RTK_FROM_OBJECT.T, np.ones(len(pts))].T
        col = (h[0] / h[2] - layout["origin"][0]) / layout["spacing"][0]
        row = det.rows - 1 - (h[1] / h[2] - layout["origin"][1]) / layout["spacing"][1]
        assert np.allclose(col, uv[n, :, 0], atol=1e-8) and np.allclose(row, uv[n, :, 1], atol=1e-8)


def test_reference_view_is_rtk_gantry_zero() -> None:
    from tests.helpers.recon import bench_detector

    g = ViewGeometry.from_carm([0.0], 0.0, 785.0, 1200.0, bench_detector(64))
    p = rtk_parameters(g)[0][0]
    assert p["GantryAngle"] == pytest.approx(0.0, abs=1e-9) or p["GantryAngle"] == pytest.approx(360.0)
    assert p["SourceToIsocenterDistance"] == pytest.approx(785.0)
    assert p["SourceToDetectorDistance"] == pytest.approx(1200.0)


def _itk_rtk():  # type: ignore[no-untyped-def]
    """``itk`` and its lazily loaded ``RTK`` module (``itk.RTK`` is not importable by name); skipped without the
    optional itk-rtk extra, except in CI (``CI`` set), which installs it and must run these tests."""
    try:
        import itk
        from itk import RTK as rtk
    except (ImportError, AttributeError):
        why = "optional itk-rtk extra not installed (pip install -e '.[rtk]')"
        if os.environ.get("CI"):
            pytest.fail(why + "; CI installs it (.ci/run)")
        pytest.skip(why)
    return itk, rtk


@pytest.mark.rtk
def test_itk_rtk_reads_the_same_matrices(random_geometry: ViewGeometry, tmp_path: Path) -> None:
    itk, rtk = _itk_rtk()
    path = tmp_path / "geometry.xml"
    write_rtk_geometry(random_geometry, path)
    reader = rtk.ThreeDCircularProjectionGeometryXMLFileReader.New()
    reader.SetFilename(str(path))
    reader.GenerateOutputInformation()  # RTK itself rejects matrices inconsistent with the parameters
    geo = reader.GetOutputObject()
    params, _ = rtk_parameters(random_geometry)
    assert len(geo.GetGantryAngles()) == len(params)
    for n, p in enumerate(params):
        m = np.asarray(itk.array_from_matrix(geo.GetMatrix(n)))
        assert np.allclose(m, rtk_matrix(p), atol=1e-6 * np.abs(m).max())


@pytest.mark.rtk
def test_itk_rtk_fdk_of_the_same_data_agrees_with_ours(tmp_path: Path) -> None:
    """RTK's CPU FDK, fed our exported geometry and projection layout, reconstructs what our FDK does."""
    from recon.fdk import fdk
    from tests.helpers.recon import (
        bench_detector,
        sphere_line_integrals,
        voxelized_spheres,
    )

    itk, rtk = _itk_rtk()
    g = ViewGeometry.from_carm(np.linspace(0, 2 * np.pi, 120, endpoint=False), 0.0, 785.0, 1200.0, bench_detector(64))
    grid = VolumeGrid.centered((40, 64, 64), 2.0)
    y = sphere_line_integrals(g).astype(np.float32)
    ours = fdk(y, grid, g, window="ram-lak")
    write_rtk_geometry(g, tmp_path / "geometry.xml")
    reader = rtk.ThreeDCircularProjectionGeometryXMLFileReader.New()
    reader.SetFilename(str(tmp_path / "geometry.xml"))
    reader.GenerateOutputInformation()
    _, layout = rtk_parameters(g)
    proj = itk.image_from_array(np.ascontiguousarray(y[:, ::-1, :]))  # RTK rows run the other way
    proj.SetSpacing([*layout["spacing"], 1.0])
    proj.SetOrigin([*layout["origin"], 0.0])
    z, yy, x = grid.coords_mm()
    ImageType = itk.Image[itk.F, 3]
    src = rtk.ConstantImageSource[ImageType].New()
    # RTK coordinates are (x, z, -y) of ours: the volume is nx by nz by ny there, its third axis runs along -y
    src.SetSize([grid.shape[2], grid.shape[0], grid.shape[1]])
    src.SetSpacing([grid.voxel_mm[0], grid.voxel_mm[2], grid.voxel_mm[1]])
    src.SetOrigin([float(x[0]), float(z[0]), float(-yy[-1])])
    src.SetConstant(0.0)
    src.Update()
    flt = rtk.FDKConeBeamReconstructionFilter[ImageType].New()
    flt.SetInput(0, src.GetOutput())
    flt.SetInput(1, proj)
    flt.SetGeometry(reader.GetOutputObject())
    flt.Update()
    theirs = itk.array_from_image(flt.GetOutput())[::-1].transpose(1, 0, 2)  # (ny, nz, nx) reversed y -> (nz, ny, nx)
    truth = voxelized_spheres(grid)
    core = (slice(10, 30), slice(None), slice(None))  # slabs with complete cone-beam data
    diff = float(np.sqrt(np.mean((ours[core] - theirs[core]) ** 2)))
    err_ours = float(np.sqrt(np.mean((ours[core] - truth[core]) ** 2)))
    err_theirs = float(np.sqrt(np.mean((theirs[core] - truth[core]) ** 2)))
    # measured: correlation 1 - 2e-13, difference 1e-7 of the peak (float32 rounding): the same FDK
    assert np.corrcoef(ours[core].ravel(), theirs[core].ravel())[0, 1] > 0.9999
    assert diff < 1e-4 * float(truth.max())
    assert err_ours < 1.01 * err_theirs


def test_astra_vectors_are_ours(random_geometry: ViewGeometry) -> None:
    grid = VolumeGrid.centered((10, 12, 14), 1.5)
    a = astra_geometries(grid, random_geometry)
    kind, rows, cols, vec = a["proj_geom"]
    assert kind == "cone_vec" and (rows, cols) == random_geometry.panel.shape
    assert np.array_equal(vec, random_geometry.vectors)
    assert a["vol_geom"][:3] == (12, 14, 10) and a["vol_geom"][3] == pytest.approx(-14 * 1.5 / 2)


def test_wire_fwhm_of_gaussian_line() -> None:
    grid = VolumeGrid.centered((8, 61, 61), 0.1)
    z, y, x = grid.coords_mm()
    sigma = 0.3
    yy, xx = np.meshgrid(y - 0.12, x + 0.05, indexing="ij")
    vol = np.broadcast_to(np.exp(-(xx**2 + yy**2) / (2 * sigma**2)), grid.shape).astype(np.float32) + 0.02
    res = wire_fwhm(vol, grid, axis="z", search_mm=2.5)
    assert res["fwhm_mm"] == pytest.approx(2.3548 * sigma, rel=0.02)
    assert res["peak_a_mm"] == pytest.approx(0.1, abs=0.11)
    flat = np.full(grid.shape, 0.02, np.float32)
    assert np.isnan(wire_fwhm(flat, grid)["fwhm_mm"])
