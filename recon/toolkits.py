"""A scan's per-view geometry in the terms of other reconstruction toolkits: ASTRA, tomosipo, LEAP and diffct.

Each export is a JSON document: the toolkit call it feeds, its arguments (arrays as nested lists, in the toolkit's
axis order and units: millimetres everywhere), how orbitct's frames map onto the toolkit's projection array, the
volume convention, and ``approximation_px``: how far (in pixels) a point in the field of view lands from where
orbitct projects it, when the toolkit's model cannot hold the geometry exactly (LEAP's detector axes are
orthogonal; 0 where the export is exact). Conventions come from each toolkit's documentation (see the how-to).
"""

from __future__ import annotations

from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from orbitct.geometry import ViewGeometry
from recon.errors import ReconError

Toolkit = Literal["astra", "tomosipo", "leap", "diffct"]
TOOLKITS: tuple[Toolkit, ...] = ("astra", "tomosipo", "leap", "diffct")
FIELD_OF_VIEW_POINTS = 5  # per axis: the points whose projections measure an export's approximation


def _finite(geometry: ViewGeometry) -> ViewGeometry:
    """The views a toolkit can take: refused with the count when some have no geometry."""
    bad = int(np.sum(~geometry.valid))
    if bad:
        raise ReconError(
            f"{bad} of {geometry.n_views} views have no geometry (their calibration failed): a toolkit needs every "
            "view; export the projections' views only (the nominal geometry, or recalibrate)"
        )
    return geometry


def _unit(a: NDArray[np.float64]) -> NDArray[np.float64]:
    return a / np.linalg.norm(a, axis=1, keepdims=True)


def field_of_view_points(geometry: ViewGeometry) -> NDArray[np.float64]:
    """Points filling the cube the panel sees at the isocenter (mm): where an export's approximation is measured."""
    half = (
        0.5
        * float(np.median(geometry.sod() / geometry.sdd))
        * min(geometry.panel.cols * geometry.panel.pitch_col, geometry.panel.rows * geometry.panel.pitch_row)
    )
    axis = np.linspace(-half, half, FIELD_OF_VIEW_POINTS)
    return np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), axis=-1).reshape(-1, 3)


def approximation_px(geometry: ViewGeometry, modelled: ViewGeometry) -> float:
    """The largest distance (pixels) between where ``geometry`` and a toolkit's ``modelled`` one project a point of
    the field of view."""
    points = field_of_view_points(geometry)
    return float(np.nanmax(np.linalg.norm(geometry.project(points) - modelled.project(points), axis=-1)))


def _leap(geometry: ViewGeometry) -> tuple[dict[str, Any], ViewGeometry]:
    col = _unit(geometry.u)
    v_across = geometry.v - np.sum(geometry.v * col, axis=1, keepdims=True) * col  # LEAP's axes are orthogonal
    row = _unit(v_across)
    width, height = np.linalg.norm(geometry.u, axis=1), np.linalg.norm(geometry.v, axis=1)
    if np.ptp(width) > 1e-9 * width.max() or np.ptp(height) > 1e-9 * height.max():
        raise ReconError("LEAP takes one pixel size for every view; this geometry's pixel sizes change between views")
    modelled = geometry.with_vectors(np.hstack([geometry.S, geometry.D, col * width[:, None], row * height[:, None]]))
    panel = geometry.panel
    arguments = {
        "numAngles": geometry.n_views,
        "numRows": panel.rows,
        "numCols": panel.cols,
        "pixelHeight": float(height[0]),
        "pixelWidth": float(width[0]),
        "sourcePositions": geometry.S,
        "moduleCenters": geometry.D,
        "rowVectors": row,
        "colVectors": col,
    }
    return arguments, modelled


def toolkit_geometry(geometry: ViewGeometry, toolkit: Toolkit) -> dict[str, Any]:
    """The JSON-ready export of ``geometry`` (all its views finite) for ``toolkit``."""
    if toolkit not in TOOLKITS:
        raise ReconError(f"toolkit {toolkit!r}: choose one of {', '.join(TOOLKITS)}")
    g = _finite(geometry)
    panel = g.panel
    exact = g
    if toolkit == "astra":
        call = "astra.create_proj_geom('cone_vec', DetectorRowCount, DetectorColCount, Vectors)"
        arguments: dict[str, Any] = {
            "DetectorRowCount": panel.rows,
            "DetectorColCount": panel.cols,
            "Vectors": g.vectors,
        }
        projections = "ASTRA's projection data are (rows, views, cols): orbitct's frames (views, rows, cols) transposed"
        volume = (
            "volume data (z, y, x) in the same frame: astra.create_vol_geom(ny, nx, nz, min_x, max_x, min_y, max_y, "
            "min_z, max_z) with the grid's extent in mm"
        )
    elif toolkit == "tomosipo":
        call = "tomosipo.cone_vec(shape=shape, src_pos=src_pos, det_pos=det_pos, det_v=det_v, det_u=det_u)"
        arguments = {
            "shape": [panel.rows, panel.cols],
            "src_pos": g.S[:, ::-1],
            "det_pos": g.D[:, ::-1],
            "det_v": g.v[:, ::-1],
            "det_u": g.u[:, ::-1],
        }
        projections = "tomosipo's projection data are (rows, views, cols): orbitct's frames transposed, as for ASTRA"
        volume = "tomosipo's vectors are (z, y, x): orbitct's (x, y, z) reversed; ts.volume(shape, pos, size) in mm"
    elif toolkit == "leap":
        call = (
            "leapct.set_modularbeam(numAngles, numRows, numCols, pixelHeight, pixelWidth, sourcePositions, "
            "moduleCenters, rowVectors, colVectors) (arrays as float32, C-contiguous)"
        )
        arguments, exact = _leap(g)
        projections = "LEAP's projection data are (numAngles, numRows, numCols): orbitct's frames as they are"
        volume = (
            "volume data (z, y, x) in the same frame: leapct.set_volume(numX, numY, numZ, voxelWidth, voxelHeight, "
            "offsetX, offsetY, offsetZ) with the offsets at the grid's centre in mm"
        )
    else:
        call = (
            "diffct.ConeProjectorFunction.apply(volume, src_pos, det_center, det_u_vec, det_v_vec, det_u, det_v, du, "
            "dv, voxel_spacing) (arrays as torch float32 tensors)"
        )
        arguments = {
            "src_pos": g.S,
            "det_center": g.D,
            "det_u_vec": _unit(g.u),
            "det_v_vec": _unit(g.v),
            "det_u": panel.cols,
            "det_v": panel.rows,
            "du": float(np.linalg.norm(g.u, axis=1)[0]),
            "dv": float(np.linalg.norm(g.v, axis=1)[0]),
        }
        exact = g.with_vectors(
            np.hstack([g.S, g.D, arguments["det_u_vec"] * arguments["du"], arguments["det_v_vec"] * arguments["dv"]])
        )
        projections = "diffct's sinogram is (views, det_u, det_v): orbitct's frames (views, rows, cols) transposed"
        volume = (
            "diffct's volume is (z, y, x) centred on the origin (orbitct's isocenter) with voxel_spacing in mm; "
            "for a grid centred elsewhere, subtract its centre from src_pos and det_center"
        )
    return {
        "toolkit": toolkit,
        "call": call,
        "arguments": {k: v.tolist() if isinstance(v, np.ndarray) else v for k, v in arguments.items()},
        "projections": projections,
        "volume": volume,
        "units": "mm",
        "views": g.n_views,
        "approximation_px": approximation_px(g, exact),
    }
