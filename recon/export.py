"""Volume exports (NIfTI, TIFF stack, PNG slices with scale bar) and geometry exports (ASTRA, RTK)."""

from __future__ import annotations

import io
import math
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from orbitct.geometry import Panel, ViewGeometry, VolumeGrid
from recon.errors import ReconError

FORMATS = ("nifti", "tiff", "png")

# RTK assumes rotation about its y axis; our orbits turn about z.  RTK coordinates are
# x_rtk = RTK_FROM_OBJECT @ x_obj, i.e. (x, z, -y): our reference view becomes RTK gantry angle 0.
RTK_FROM_OBJECT = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


def grid_affine(grid: VolumeGrid) -> NDArray[np.float64]:
    """4x4 map from voxel indices (x, y, z) to object-frame mm."""
    aff = np.diag(list(grid.voxel_mm) + [1.0])
    aff[:3, 3] = grid.origin_mm
    return aff


def export_nifti(volume: NDArray[np.float32], grid: VolumeGrid, path: Path) -> Path:
    """Write a NIfTI-1 file (data indexed x, y, z; affine in object-frame mm; values 1/mm)."""
    import nibabel as nib

    img = nib.Nifti1Image(np.ascontiguousarray(np.transpose(volume, (2, 1, 0)), dtype=np.float32), grid_affine(grid))
    img.header.set_xyzt_units("mm")
    nib.save(img, str(path))
    return path


def export_tiff(volume: NDArray[np.float32], grid: VolumeGrid, path: Path) -> Path:
    """Write a float32 multi-page TIFF (one page per z slice) with ImageJ spacing metadata."""
    import tifffile

    vx, vy, vz = grid.voxel_mm
    tifffile.imwrite(
        str(path),
        np.asarray(volume, dtype=np.float32),
        imagej=True,
        resolution=(1.0 / vx, 1.0 / vy),
        metadata={"spacing": vz, "unit": "mm", "axes": "ZYX"},
    )
    return path


def _scale_bar_mm(width_mm: float) -> float:
    target = width_mm / 5
    base = 10 ** math.floor(math.log10(target))
    return float(max(m * base for m in (1, 2, 5) if m * base <= target))


def display_window(volume: NDArray[np.float32], metal_mu: float = 0.1) -> tuple[float, float, str]:
    """Grey window ``(lo, hi, note)``: the 1st to 99.5th percentile, of the voxels below ``metal_mu`` (1/mm) when
    metal is present, so that steel does not push the anatomy into black; ``note`` says so."""
    sample = np.asarray(volume[:: max(1, volume.shape[0] // 64)], dtype=np.float32).ravel()
    sample = sample[np.isfinite(sample)]
    if sample.size == 0:
        return 0.0, 1.0, ""
    metal = sample > metal_mu
    note = ""
    if 0 < metal.mean() < 0.5:
        sample = sample[~metal]
        note = f"; metal above {metal_mu:g}/mm saturates"
    lo, hi = (float(v) for v in np.percentile(sample, [1.0, 99.5]))
    return lo, max(hi, lo + 1e-9), note


def slice_views(
    volume: NDArray[np.float32], grid: VolumeGrid, index: dict[str, int] | None = None
) -> dict[str, tuple[NDArray[np.float32], tuple[float, ...], str, str]]:
    """Axial, coronal and sagittal slices (the middle ones unless ``index`` says) with extents (mm) and axis labels."""
    nz, ny, nx = volume.shape
    at = {"axial": nz // 2, "coronal": ny // 2, "sagittal": nx // 2, **(index or {})}
    ext = grid.extent_mm
    return {
        "axial": (volume[at["axial"]], (ext[0, 0], ext[0, 1], ext[1, 0], ext[1, 1]), "x (mm)", "y (mm)"),
        "coronal": (volume[:, at["coronal"], :], (ext[0, 0], ext[0, 1], ext[2, 0], ext[2, 1]), "x (mm)", "z (mm)"),
        "sagittal": (volume[:, :, at["sagittal"]], (ext[1, 0], ext[1, 1], ext[2, 0], ext[2, 1]), "y (mm)", "z (mm)"),
    }


def _draw_slice(
    ax: Any,
    img: NDArray[np.float32],
    extent: tuple[float, ...],
    window: tuple[float, float],
    xlabel: str,
    ylabel: str,
    title: str,
) -> None:
    from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

    ax.imshow(img, cmap="gray", vmin=window[0], vmax=window[1], extent=extent, origin="lower", interpolation="nearest")
    bar = _scale_bar_mm(extent[1] - extent[0])
    ax.add_artist(
        AnchoredSizeBar(
            ax.transData,
            bar,
            f"{bar:g} mm",
            "lower right",
            pad=0.4,
            color="yellow",
            frameon=False,
            size_vertical=(extent[3] - extent[2]) / 150,
        )
    )
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize=9)


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def export_png(
    volume: NDArray[np.float32], grid: VolumeGrid, stem: Path, window: tuple[float, float] | None = None
) -> list[Path]:
    """Central axial, coronal and sagittal slices as PNGs with axes in mm and a scale bar."""
    plt = _pyplot()
    lo, hi, note = (*window, "") if window is not None else display_window(volume)
    out = []
    for label, (img, extent, xl, yl) in slice_views(volume, grid).items():
        fig, ax = plt.subplots(figsize=(5, 5 * (extent[3] - extent[2]) / max(extent[1] - extent[0], 1e-9) + 0.5))
        _draw_slice(ax, img, extent, (lo, hi), xl, yl, f"{label} (1/mm, window {lo:.3g}..{hi:.3g}{note})")
        path = stem.with_name(f"{stem.name}_{label}.png")
        fig.savefig(path, dpi=100, bbox_inches="tight")
        plt.close(fig)
        out.append(path)
    return out


def slice_png(
    volume: NDArray[np.float32],
    grid: VolumeGrid,
    axis: str,
    index: int,
    title: str = "",
    window: tuple[float, float, str] | None = None,
) -> bytes:
    """One slice as PNG bytes: axes in mm, a scale bar, the display window in the title (the volume's own, metal
    excluded, unless ``window`` gives another's, as :func:`display_window` makes it)."""
    plt = _pyplot()
    lo, hi, note = display_window(volume) if window is None else window
    img, extent, xl, yl = slice_views(volume, grid, {axis: index})[axis]
    fig, ax = plt.subplots(figsize=(5, 5 * (extent[3] - extent[2]) / max(extent[1] - extent[0], 1e-9) + 0.5))
    _draw_slice(
        ax, img, extent, (lo, hi), xl, yl, f"{title}{axis} slice {index} (1/mm, window {lo:.3g}..{hi:.3g}{note})"
    )
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100, bbox_inches="tight")
    plt.close(fig)
    return buf.getvalue()


def export_comparison(
    volumes: Sequence[tuple[str, NDArray[np.float32]]], grid: VolumeGrid, path: Path, title: str
) -> Path:
    """One figure, a row per volume (e.g. calibrated and nominal geometry), central slices in one shared grey
    window (that of the first volume), each row titled with its label, the figure with ``title``."""
    plt = _pyplot()
    lo, hi, note = display_window(volumes[0][1])
    fig, axes = plt.subplots(len(volumes), 3, figsize=(12, 4 * len(volumes)), squeeze=False)
    for row, (label, vol) in enumerate(volumes):
        for col, (view, (img, extent, xl, yl)) in enumerate(slice_views(vol, grid).items()):
            _draw_slice(axes[row, col], img, extent, (lo, hi), xl, yl, f"{label}: {view}")
    fig.suptitle(f"{title}\nsame grey window for every panel: {lo:.3g}..{hi:.3g} 1/mm{note}", fontsize=11)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def export_volume(volume: NDArray[np.float32], grid: VolumeGrid, formats: list[str], stem: Path) -> list[Path]:
    """Write ``volume`` in each of ``formats`` next to ``stem``; returns the files written."""
    bad = [f for f in formats if f not in FORMATS]
    if bad:
        raise ReconError(f"unknown export format(s) {bad}; choose from {FORMATS}")
    stem.parent.mkdir(parents=True, exist_ok=True)
    files: list[Path] = []
    for fmt in formats:
        if fmt == "nifti":
            files.append(export_nifti(volume, grid, stem.with_name(stem.name + ".nii.gz")))
        elif fmt == "tiff":
            files.append(export_tiff(volume, grid, stem.with_name(stem.name + ".tif")))
        else:
            files.extend(export_png(volume, grid, stem))
    return files


# ------------------------------------------------------------------ ASTRA
def astra_geometries(grid: VolumeGrid, geometry: ViewGeometry) -> dict[str, Any]:
    """Arguments for ``astra.create_proj_geom('cone_vec', ...)`` and ``astra.create_vol_geom(...)``.

    ASTRA's ``cone_vec`` rows are our ``S, D, u, v`` unchanged (object-frame mm); its volume
    data are indexed (z, y, x) like ours, and its projection data (rows, views, cols).
    """
    ext = grid.extent_mm
    nz, ny, nx = grid.shape
    return {
        "proj_geom": ("cone_vec", geometry.panel.rows, geometry.panel.cols, np.array(geometry.vectors)),
        "vol_geom": (ny, nx, nz, ext[0, 0], ext[0, 1], ext[1, 0], ext[1, 1], ext[2, 0], ext[2, 1]),
    }


# -------------------------------------------------------------------- RTK
def _rtk_euler(R: NDArray[np.float64]) -> tuple[float, float, float]:
    """(gantry, out-of-plane, in-plane) degrees with ``R = Rz(-ip) Rx(-oop) Ry(-g)``."""
    b = math.asin(max(-1.0, min(1.0, R[2, 1])))
    c = math.atan2(-R[2, 0], R[2, 2])
    a = math.atan2(-R[0, 1], R[1, 1])
    return tuple(float(np.degrees(-t) % 360.0) for t in (c, b, a))  # type: ignore[return-value]


def _rtk_rotation(g_deg: float, oop_deg: float, ip_deg: float) -> NDArray[np.float64]:
    a, b, c = (-np.radians(t) for t in (ip_deg, oop_deg, g_deg))
    rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    rx = np.array([[1, 0, 0], [0, np.cos(b), -np.sin(b)], [0, np.sin(b), np.cos(b)]])
    ry = np.array([[np.cos(c), 0, np.sin(c)], [0, 1, 0], [-np.sin(c), 0, np.cos(c)]])
    return rz @ rx @ ry


def rtk_matrix(p: dict[str, float]) -> NDArray[np.float64]:
    """RTK's 3x4 projection matrix (physical detector mm) from its 9 parameters."""
    sid, sdd = p["SourceToIsocenterDistance"], p["SourceToDetectorDistance"]
    sx, sy = p["SourceOffsetX"], p["SourceOffsetY"]
    px, py = p["ProjectionOffsetX"], p["ProjectionOffsetY"]
    shift2 = np.array([[1, 0, sx - px], [0, 1, sy - py], [0, 0, 1.0]])
    persp = np.array([[-sdd, 0, 0, 0], [0, -sdd, 0, 0], [0, 0, 1, -sid]])
    shift3 = np.eye(4)
    shift3[0, 3], shift3[1, 3] = -sx, -sy
    rot = np.eye(4)
    rot[:3, :3] = _rtk_rotation(p["GantryAngle"], p["OutOfPlaneAngle"], p["InPlaneAngle"])
    return shift2 @ persp @ shift3 @ rot


def rtk_parameters(geometry: ViewGeometry) -> tuple[list[dict[str, float]], dict[str, Any]]:
    """Per-view RTK parameters and the projection image layout RTK must use.

    The layout: rows are flipped (RTK row ``j`` = our row ``rows-1-j``), spacing = pitches,
    origin = minus the centre offset; volumes live in RTK coordinates ``RTK_FROM_OBJECT @ x``.
    """
    det = geometry.panel
    if not geometry.valid.all():
        raise ReconError("RTK export needs finite geometry for every view")
    Q = RTK_FROM_OBJECT
    params = []
    max_skew = 0.0
    for S, D, u, v in zip(geometry.S @ Q.T, geometry.D @ Q.T, geometry.u @ Q.T, geometry.v @ Q.T):
        rx = u / np.linalg.norm(u)
        vp = v - (v @ rx) * rx
        max_skew = max(max_skew, abs(float(v @ rx)) / float(np.linalg.norm(v)))
        ry = -vp / np.linalg.norm(vp)
        rz = np.cross(rx, ry)
        R = np.stack([rx, ry, rz])
        s, d = R @ S, R @ D
        g, oop, ip = _rtk_euler(R)
        params.append(
            {
                "GantryAngle": g,
                "OutOfPlaneAngle": oop,
                "InPlaneAngle": ip,
                "SourceToIsocenterDistance": float(s[2]),
                "SourceToDetectorDistance": float(s[2] - d[2]),
                "SourceOffsetX": float(s[0]),
                "SourceOffsetY": float(s[1]),
                "ProjectionOffsetX": float(d[0]),
                "ProjectionOffsetY": float(d[1]),
            }
        )
    c0, r0 = det.center
    layout = {
        "size": (det.cols, det.rows),
        "spacing": (det.pitch_col, det.pitch_row),
        "origin": (-c0 * det.pitch_col, -r0 * det.pitch_row),
        "rows_flipped": True,
        "max_skew": max_skew,
        "rtk_from_object": Q.tolist(),
    }
    return params, layout


def write_rtk_geometry(geometry: ViewGeometry, path: Path) -> dict[str, Any]:
    """Write an RTK ``ThreeDCircularProjectionGeometry`` XML file (version 3) with matrices; returns the layout."""
    params, layout = rtk_parameters(geometry)
    root = ET.Element("RTKThreeDCircularGeometry", version="3")
    for p in params:
        proj = ET.SubElement(root, "Projection")
        for key, val in p.items():
            ET.SubElement(proj, key).text = repr(float(val))
        m = rtk_matrix(p)
        ET.SubElement(proj, "Matrix").text = "\n" + "\n".join(" ".join(f"{x:.17g}" for x in row) for row in m) + "\n"
    ET.indent(root)
    body = ET.tostring(root, encoding="unicode")
    Path(path).write_text('<?xml version="1.0"?>\n<!DOCTYPE RTKGEOMETRY>\n' + body + "\n")
    return layout


def read_rtk_geometry(path: Path, detector: Panel) -> ViewGeometry:
    """Our views from an RTK XML file written by :func:`write_rtk_geometry` (same detector layout)."""
    root = ET.parse(str(path)).getroot()
    keys = (
        "GantryAngle",
        "OutOfPlaneAngle",
        "InPlaneAngle",
        "SourceToIsocenterDistance",
        "SourceToDetectorDistance",
        "SourceOffsetX",
        "SourceOffsetY",
        "ProjectionOffsetX",
        "ProjectionOffsetY",
    )
    glob = {k: float(root.findtext(k, "")) for k in keys if root.find(k) is not None}
    rows = []
    for proj in root.findall("Projection"):
        p = {
            "OutOfPlaneAngle": 0.0,
            "InPlaneAngle": 0.0,
            "SourceOffsetX": 0.0,
            "SourceOffsetY": 0.0,
            "ProjectionOffsetX": 0.0,
            "ProjectionOffsetY": 0.0,
            **glob,
        }
        p.update({k: float(proj.findtext(k, "")) for k in keys if proj.find(k) is not None})
        R = _rtk_rotation(p["GantryAngle"], p["OutOfPlaneAngle"], p["InPlaneAngle"])
        s = np.array([p["SourceOffsetX"], p["SourceOffsetY"], p["SourceToIsocenterDistance"]])
        d = np.array(
            [
                p["ProjectionOffsetX"],
                p["ProjectionOffsetY"],
                p["SourceToIsocenterDistance"] - p["SourceToDetectorDistance"],
            ]
        )
        back = RTK_FROM_OBJECT.T @ R.T
        rows.append(
            np.concatenate(
                [
                    back @ s,
                    back @ d,
                    back @ np.array([detector.pitch_col, 0, 0]),
                    back @ np.array([0, -detector.pitch_row, 0]),
                ]
            )
        )
    return ViewGeometry(np.array(rows), detector)
