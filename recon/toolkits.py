"""A scan's per-view geometry in the terms of other reconstruction toolkits: ASTRA, tomosipo, LEAP, diffct, TIGRE and
CIL.

Each export is a JSON document: the toolkit call it feeds, its arguments (arrays as nested lists, in the toolkit's
axis order and units: millimetres everywhere), how orbitct's frames map onto the toolkit's projection array, the
volume convention, and ``approximation_px``: how far (in pixels) a point in the field of view lands from where
orbitct projects it, when the toolkit's model cannot hold the geometry exactly (LEAP's, TIGRE's and CIL's detector axes
are orthogonal, with one pixel size for every view; 0 where the export is exact). Conventions come from each toolkit's documentation (see the how-to).
"""

from __future__ import annotations

from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from orbitct.geometry import ViewGeometry
from orbitct.rotations import rot_x, rot_y, rot_z
from recon.errors import ReconError

Toolkit = Literal["astra", "tomosipo", "leap", "diffct", "tigre", "cil"]
TOOLKITS: tuple[Toolkit, ...] = ("astra", "tomosipo", "leap", "diffct", "tigre", "cil")
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


def _orthogonal_panel(
    geometry: ViewGeometry, toolkit: str
) -> tuple[NDArray[np.float64], NDArray[np.float64], float, float, ViewGeometry]:
    """Unit column and row directions (the row direction made orthogonal to the column direction), the pixel width
    and height, and the geometry they describe: what a toolkit with orthogonal detector axes and one pixel size
    holds of ``geometry``."""
    col = _unit(geometry.u)
    row = _unit(geometry.v - np.sum(geometry.v * col, axis=1, keepdims=True) * col)
    width, height = np.linalg.norm(geometry.u, axis=1), np.linalg.norm(geometry.v, axis=1)
    if np.ptp(width) > 1e-9 * width.max() or np.ptp(height) > 1e-9 * height.max():
        raise ReconError(
            f"{toolkit} takes one pixel size for every view; this geometry's pixel sizes change between views"
        )
    modelled = geometry.with_vectors(np.hstack([geometry.S, geometry.D, col * width[:, None], row * height[:, None]]))
    return col, row, float(width[0]), float(height[0]), modelled


def _leap(geometry: ViewGeometry) -> tuple[dict[str, Any], ViewGeometry]:
    col, row, width, height, modelled = _orthogonal_panel(geometry, "LEAP")
    panel = geometry.panel
    arguments = {
        "numAngles": geometry.n_views,
        "numRows": panel.rows,
        "numCols": panel.cols,
        "pixelHeight": height,
        "pixelWidth": width,
        "sourcePositions": geometry.S,
        "moduleCenters": geometry.D,
        "rowVectors": row,
        "colVectors": col,
    }
    return arguments, modelled


def _cil(geometry: ViewGeometry) -> tuple[dict[str, Any], ViewGeometry]:
    """CIL's Cone3D_Flex with the panel's origin at its bottom left: pixel (0, 0) of a frame is where column and row
    numbers start, the x direction along the columns, the y direction along the rows."""
    col, row, width, height, modelled = _orthogonal_panel(geometry, "CIL")
    panel = geometry.panel
    arguments = {
        "source_position_set": geometry.S,
        "detector_position_set": geometry.D,
        "detector_direction_x_set": col,
        "detector_direction_y_set": row,
        "volume_centre_position": [0.0, 0.0, 0.0],
        "units": "mm",
        "num_pixels": [panel.cols, panel.rows],
        "pixel_size": [width, height],
        "origin": "bottom-left",
    }
    return arguments, modelled


def _zyz_angles(R: NDArray[np.float64]) -> NDArray[np.float64]:
    """``(alpha, theta, psi)`` with ``R = Rz(alpha) Ry(theta) Rz(psi)`` (TIGRE's ``eulerZYZ``), per view."""
    theta = np.arctan2(np.hypot(R[:, 2, 0], R[:, 2, 1]), R[:, 2, 2])
    locked = np.sin(theta) < 1e-9  # theta = 0 (or pi): only alpha + psi is defined; psi = 0
    alpha = np.where(locked, np.arctan2(R[:, 1, 0], R[:, 0, 0]), np.arctan2(R[:, 1, 2], R[:, 0, 2]))
    psi = np.where(locked, 0.0, np.arctan2(R[:, 2, 1], -R[:, 2, 0]))
    return np.stack([alpha, theta, psi], axis=1)


def tigre_vectors(arguments: dict[str, Any]) -> NDArray[np.float64]:
    """orbitct's ``(N, 12)`` vectors of the views a TIGRE geometry (as :func:`toolkit_geometry` writes it) describes."""
    angles = np.asarray(arguments["angles"], dtype=float)
    R = rot_z(angles[:, 0]) @ rot_y(angles[:, 1]) @ rot_z(angles[:, 2])
    yaw, pitch, roll = np.asarray(arguments["rotDetector"], dtype=float).T
    detector = R @ rot_z(roll) @ rot_y(pitch) @ rot_x(yaw)
    dso, dsd = np.asarray(arguments["DSO"], dtype=float), np.asarray(arguments["DSD"], dtype=float)
    off_v, off_u = np.asarray(arguments["offDetector"], dtype=float).T
    origin = np.asarray(arguments["offOrigin"], dtype=float)[:, ::-1]  # TIGRE's Python order is (z, y, x)
    d_v, d_u = arguments["dDetector"]
    source = np.einsum("nij,nj->ni", R, np.stack([dso, 0 * dso, 0 * dso], 1)) - origin
    centre = np.einsum("nij,nj->ni", R, np.stack([dso - dsd, off_u, off_v], 1)) - origin
    return np.hstack([source, centre, d_u * detector[:, :, 1], -d_v * detector[:, :, 2]])


def _tigre(geometry: ViewGeometry) -> tuple[dict[str, Any], ViewGeometry]:
    """TIGRE's cone geometry: per view the source on the rotated x axis at DSO, the detector at DSD with its offsets and
    roll/pitch/yaw, the ZYZ angles; the image at the origin (offOrigin 0)."""
    dso = np.linalg.norm(geometry.S, axis=1)
    x = geometry.S / dso[:, None]
    u = _unit(geometry.u)
    y = _unit(u - np.sum(u * x, axis=1, keepdims=True) * x)
    R = np.stack([x, y, np.cross(x, y)], axis=2)  # columns: TIGRE's rotated axes in orbitct's frame
    local = np.einsum("nji,nj->ni", R, geometry.D)
    dsd = dso - local[:, 0]
    if np.any(dsd <= dso):
        raise ReconError("TIGRE needs the detector beyond the origin from the source in every view; this one is not")
    along_u = np.einsum("nji,nj->ni", R, u)
    along_v = np.einsum("nji,nj->ni", R, _unit(geometry.v))
    up = -along_v + np.sum(along_v * along_u, axis=1, keepdims=True) * along_u  # TIGRE's rows run down its z axis
    detector = np.stack([np.cross(along_u, _unit(up)), along_u, _unit(up)], axis=2)
    pitch = -np.arcsin(np.clip(detector[:, 2, 0], -1.0, 1.0))
    yaw = np.arctan2(detector[:, 2, 1], detector[:, 2, 2])
    roll = np.arctan2(detector[:, 1, 0], detector[:, 0, 0])
    panel = geometry.panel
    d_u, d_v = (
        float(np.median(np.linalg.norm(geometry.u, axis=1))),
        float(np.median(np.linalg.norm(geometry.v, axis=1))),
    )
    arguments = {
        "mode": "cone",
        "DSO": dso,
        "DSD": dsd,
        "nDetector": [panel.rows, panel.cols],
        "dDetector": [d_v, d_u],
        "sDetector": [panel.rows * d_v, panel.cols * d_u],
        "offDetector": np.stack([local[:, 2], local[:, 1]], axis=1),
        "rotDetector": np.stack([yaw, pitch, roll], axis=1),
        "offOrigin": np.zeros((geometry.n_views, 3)),
        "COR": np.zeros(geometry.n_views),
        "angles": _zyz_angles(R),
    }
    return arguments, geometry.with_vectors(tigre_vectors(arguments))


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
    elif toolkit == "cil":
        call = (
            "AcquisitionGeometry.create_Cone3D_Flex(source_position_set, detector_position_set, "
            "detector_direction_x_set, detector_direction_y_set, volume_centre_position, units)"
            ".set_panel(num_pixels, pixel_size, origin)"
        )
        arguments, exact = _cil(g)
        projections = "CIL's acquisition data are (projection, vertical, horizontal): orbitct's frames as they are"
        volume = (
            "an ImageGeometry (vertical, horizontal_y, horizontal_x) = (z, y, x) in the same frame, centred on "
            "volume_centre_position (mm): set it to the grid's centre"
        )
    elif toolkit == "tigre":
        call = (
            "geo = tigre.geometry(); set geo.<name> = arguments[name] (arrays as numpy float32, one row per view); "
            "tigre.Ax(image, geo, arguments['angles'])"
        )
        arguments, exact = _tigre(g)
        projections = "TIGRE's projections are (views, nDetector[0], nDetector[1]): orbitct's frames as they are"
        volume = (
            "TIGRE's image is (z, y, x) in the same frame, centred on offOrigin (Python order (z, y, x), mm): set each "
            "view's offOrigin to the grid's centre, reversed, to reconstruct a grid centred elsewhere"
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
