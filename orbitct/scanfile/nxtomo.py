"""A scan file as NXtomo (NeXus), the format of synchrotron and lab tomography tools (tomwer, nabu, silx view).

The ``nxtomo`` library writes the application definition: every frame with its image key (the scan file
already numbers them as NXtomo does), the rotation angle per frame, pixel sizes, the source-to-sample and
sample-to-detector distances, and the title and times. A cone-beam orbit with tilts is more than one
rotation axis, so beside NXtomo's fields the entry gets ``sample/transformations`` (NXtransformations:
the per-frame rotation about z, the tilt about x and, on a bench, the hexapod's translations, as NeXus
``depends_on`` chains) and an ``orbitct`` NXcollection with the full per-view geometry (ASTRA ``cone_vec``
vectors, object frame, mm) of every geometry the file holds.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import h5py
import numpy as np

from orbitct.scanfile.errors import ScanFileError
from orbitct.scanfile.reader import ScanFile

ENTRY = "entry0000"
ROTATION_AXES = ("rotation_stage.R", "carm.primary", "orbit.rotation")  # degrees, about z
TILT_AXES = ("carm.secondary", "orbit.tilt", "hexapod.U")  # degrees, about x
TRANSLATION_AXES = (("hexapod.X", (1.0, 0.0, 0.0)), ("hexapod.Y", (0.0, 1.0, 0.0)), ("hexapod.Z", (0.0, 0.0, 1.0)))


def _positions(encoders: dict[str, np.ndarray], commanded: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Per axis and frame: the encoder read-back where there is one, else the commanded position."""
    out = dict(commanded)
    for name, read in encoders.items():
        out[name] = np.where(np.isfinite(read), read, commanded.get(name, read))
    return out


def _first(axes: dict[str, np.ndarray], names: tuple[str, ...]) -> tuple[str, np.ndarray] | None:
    for name in names:
        if name in axes:
            return name, axes[name]
    return None


def export_nxtomo(scan: str | Path, out: str | Path, *, overwrite: bool = False) -> Path:
    """Write ``scan`` as an NXtomo file ``out`` (entry ``entry0000``); frames are copied."""
    try:
        from nxtomo import NXtomo
        from pint import get_application_registry
    except ImportError:
        raise ScanFileError("NXtomo export needs the nxtomo library: pip install 'orbitct[nexus]'") from None
    out = Path(out)
    if out.exists() and not overwrite:
        raise ScanFileError(f"{out} exists; choose another name or overwrite it")
    ureg = get_application_registry()
    with ScanFile(scan) as sf:
        n = sf.n_frames
        keys = np.asarray(sf.image_key, dtype=np.uint8)
        axes = _positions(sf.axes("encoders"), sf.axes("commanded"))
        nominal = sf.geometry("nominal")
        geometries = {g: sf.geometry(g).vectors for g in ("nominal", "calibrated", "truth") if sf.has_geometry(g)}
        rows, cols = sf.panel.shape
        pitch_col, pitch_row = sf.panel.pitch_mm
        orbit_name, _ = sf.orbit
        data = np.asarray(sf.frames[:n])
        times = sf.time_s
        status = sf.status
    proj = keys == 0
    sod = float(np.nanmedian(nominal.sod()[proj])) if proj.any() else float("nan")
    sdd = float(np.nanmedian(nominal.sdd[proj])) if proj.any() else float("nan")
    rotation = _first(axes, ROTATION_AXES)
    nx = NXtomo()
    nx.title = f"{Path(scan).name}: {orbit_name} orbit ({status})"
    nx.instrument.detector.data = data
    nx.instrument.detector.image_key_control = keys
    nx.instrument.detector.x_pixel_size = pitch_col * ureg.millimeter
    nx.instrument.detector.y_pixel_size = pitch_row * ureg.millimeter
    nx.instrument.detector.distance = (sdd - sod) * ureg.millimeter
    nx.instrument.source.distance = sod * ureg.millimeter
    nx.instrument.source.probe = "x-ray"
    nx.sample.rotation_angle = (rotation[1] if rotation is not None else np.zeros(n)) * ureg.degree
    for name, axis in (("x_translation", "hexapod.X"), ("y_translation", "hexapod.Y"), ("z_translation", "hexapod.Z")):
        if axis in axes:
            setattr(nx.sample, name, axes[axis] * ureg.millimeter)
    nx.save(str(out), data_path=ENTRY, overwrite=overwrite)
    with h5py.File(out, "a") as f:
        _add_transformations(f[f"{ENTRY}/sample"], axes, rotation)
        _add_geometry(f[ENTRY], geometries, times, (rows, cols), (pitch_col, pitch_row), Path(scan).name)
    return out


def _add_transformations(
    sample: h5py.Group, axes: dict[str, np.ndarray], rotation: tuple[str, np.ndarray] | None
) -> None:
    """NXtransformations of the sample per frame: translations, then tilt about x, then rotation about z."""
    g = sample.require_group("transformations")
    g.attrs["NX_class"] = "NXtransformations"
    chain: list[tuple[str, np.ndarray, str, tuple[float, float, float], str]] = []
    if rotation is not None:
        chain.append(("rotation", rotation[1], "rotation", (0.0, 0.0, 1.0), "degree"))
    tilt = _first(axes, TILT_AXES)
    if tilt is not None:
        chain.append(("tilt", tilt[1], "rotation", (1.0, 0.0, 0.0), "degree"))
    for axis, vector in TRANSLATION_AXES:
        if axis in axes:
            chain.append((axis.split(".")[1].lower() + "_translation", axes[axis], "translation", vector, "mm"))
    for i, (name, values, kind, vector, unit) in enumerate(chain):
        if name in g:
            del g[name]
        ds = g.create_dataset(name, data=np.asarray(values, dtype=np.float64))
        ds.attrs.update(
            {
                "transformation_type": kind,
                "vector": np.asarray(vector),
                "units": unit,
                "depends_on": chain[i + 1][0] if i + 1 < len(chain) else ".",
            }
        )
    if chain:
        sample.attrs["depends_on"] = f"transformations/{chain[0][0]}"


def _add_geometry(
    entry: h5py.Group,
    geometries: dict[str, Any],
    times: np.ndarray,
    shape: tuple[int, int],
    pitch: tuple[float, float],
    source: str,
) -> None:
    """The per-view cone-beam geometry of every geometry in the scan file, as ``orbitct`` NXcollection."""
    g = entry.require_group("orbitct")
    g.attrs.update(
        {
            "NX_class": "NXcollection",
            "source_file": source,
            "detector_rows_cols": np.asarray(shape),
            "pitch_mm": np.asarray(pitch),
            "description": "per-view geometry: S, D, u, v (ASTRA cone_vec order) in the object frame, mm; "
            "NaN for frames that are not projections (see orbitct's geometry.md)",
        }
    )
    for name, vectors in geometries.items():
        ds = g.create_dataset(f"{name}_vectors", data=np.asarray(vectors, dtype=np.float64))
        ds.attrs["units"] = "mm"
    g.create_dataset("time_s", data=np.asarray(times, dtype=np.float64)).attrs["units"] = "s"
