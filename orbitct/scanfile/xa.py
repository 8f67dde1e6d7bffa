"""C-arm runs as DICOM X-ray angiography (XA) multi-frame objects, both ways (pydicom encodes and decodes).

``write_xa_run`` writes a C-arm scan's projections as one XA object, as a C-arm's own export does: the
positioner angles of the first frame and, per frame, their increments from it; source-to-detector and
source-to-isocenter distances; imager pixel spacing. ``import_xa`` reads one or more such runs of one orbit
(in acquisition order) into a scan file with the nominal geometry those attributes give, and records what
it had to assume (no darks and flats in an XA run: dark 0, flat the run's bright level; the principal point
at the detector centre). Angles: primary = LAO (+) / RAO (-) = orbitct's rotation ``theta``, secondary =
CRAN (+) / CAUD (-) = its tilt ``phi`` (``geometry.md``).
"""

from __future__ import annotations

import datetime as dt
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from orbitct.dicom import new_instance
from orbitct.geometry import Panel, ViewGeometry
from orbitct.scanfile.errors import ScanFileError
from orbitct.scanfile.keys import ImageKey
from orbitct.scanfile.reader import ScanFile
from orbitct.scanfile.writer import ScanWriter

AXES = {"carm.primary": "deg", "carm.secondary": "deg"}
REQUIRED = ("NumberOfFrames", "Rows", "Columns", "PositionerPrimaryAngle", "PositionerSecondaryAngle",
            "DistanceSourceToDetector", "DistanceSourceToPatient", "ImagerPixelSpacing", "PixelData")


def write_xa_run(scan: str | Path, out: str | Path, *, patient_id: str = "", part: tuple[int, int] | None = None) -> Path:
    """Write the projections of C-arm scan ``scan`` (projections ``part[0]:part[1]`` only, when given: one run of an
    orbit acquired as several) as one multi-frame XA object ``out``."""
    from pydicom.uid import XRayAngiographicImageStorage, generate_uid

    with ScanFile(scan) as sf:
        proj = sf.projection_indices
        if part is not None:
            proj = proj[part[0]:part[1]]
        if proj.size == 0:
            raise ScanFileError(f"{scan}: no projection frames to export")
        angles = {}
        for axis in AXES:
            read, cmd = sf.axes("encoders").get(axis), sf.axes("commanded").get(axis)
            if read is None and cmd is None:
                raise ScanFileError(f"{scan}: no {axis} positions: XA export is for C-arm scans")
            value = read if read is not None else cmd
            if cmd is not None:
                value = np.where(np.isfinite(value), value, cmd)
            angles[axis] = value[proj]
        nominal = sf.geometry("nominal")[proj]
        frames = np.asarray(sf.frames[proj.tolist()], dtype=np.uint16)
        pitch_col, pitch_row = sf.panel.pitch_mm
        times = sf.time_s[proj]
    sad, sdd = float(np.median(nominal.sod())), float(np.median(nominal.sdd))
    primary, secondary = angles["carm.primary"], angles["carm.secondary"]
    now = dt.datetime.now()
    ds = new_instance(XRayAngiographicImageStorage)
    ds.Modality, ds.Manufacturer, ds.ImageType = "XA", "orbitct C-arm twin", ["ORIGINAL", "PRIMARY", "SINGLE PLANE"]
    ds.PatientName, ds.PatientID, ds.PatientBirthDate, ds.PatientSex = "", patient_id or Path(scan).stem[:64], "", ""
    ds.StudyInstanceUID, ds.SeriesInstanceUID = generate_uid(), generate_uid()
    ds.StudyDate = ds.SeriesDate = ds.AcquisitionDate = ds.ContentDate = now.strftime("%Y%m%d")
    ds.StudyTime = ds.SeriesTime = ds.ContentTime = now.strftime("%H%M%S")
    ds.AcquisitionDateTime = (now + dt.timedelta(seconds=float(np.nan_to_num(times[0])))).strftime("%Y%m%d%H%M%S.%f")
    ds.StudyID, ds.SeriesNumber, ds.InstanceNumber, ds.AccessionNumber, ds.ReferringPhysicianName = "1", 1, 1, "", ""
    ds.PatientOrientation, ds.Laterality, ds.KVP, ds.RadiationSetting = "", "", "", "GR"
    ds.XRayTubeCurrent, ds.ExposureTime, ds.Exposure = "", "", ""  # the technique is in the bench configuration
    ds.PositionerMotion = "DYNAMIC"
    ds.PositionerPrimaryAngle, ds.PositionerSecondaryAngle = f"{primary[0]:.10g}", f"{secondary[0]:.10g}"
    ds.PositionerPrimaryAngleIncrement = [f"{a:.10g}" for a in primary - primary[0]]
    ds.PositionerSecondaryAngleIncrement = [f"{a:.10g}" for a in secondary - secondary[0]]
    ds.DistanceSourceToDetector, ds.DistanceSourceToPatient = f"{sdd:.10g}", f"{sad:.10g}"
    ds.ImagerPixelSpacing = [f"{pitch_row:.10g}", f"{pitch_col:.10g}"]  # row spacing, column spacing
    ds.FrameTime = f"{1000.0 * float(np.median(np.diff(times))) if times.size > 1 else 0.0:.10g}"
    ds.FrameIncrementPointer = (0x0018, 0x1063)
    ds.NumberOfFrames = int(frames.shape[0])
    ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
    ds.Rows, ds.Columns = int(frames.shape[1]), int(frames.shape[2])
    ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 0
    ds.PixelIntensityRelationship = "LIN"
    ds.PixelData = np.ascontiguousarray(frames).tobytes()
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    ds.save_as(out, enforce_file_format=True)
    return out


def _run(path: Path) -> dict[str, Any]:
    """The geometry-relevant content of one XA run, or ScanFileError naming what is missing or wrong."""
    import pydicom

    try:
        ds = pydicom.dcmread(path)
    except Exception as exc:  # noqa: BLE001 - any unreadable file is named with the reason
        raise ScanFileError(f"{path}: not a readable DICOM file ({type(exc).__name__}: {exc})") from None
    if ds.get("Modality") not in ("XA", "RF"):
        raise ScanFileError(f"{path}: modality {ds.get('Modality')!r}, expected an XA (or XRF) run")
    if "PerFrameFunctionalGroupsSequence" in ds:
        raise ScanFileError(f"{path}: Enhanced XA (per-frame functional groups) is not supported yet; export the run "
                            "as classic multi-frame XA")
    missing = [k for k in REQUIRED if k not in ds or ds.get(k) in (None, "")]
    if missing:
        raise ScanFileError(f"{path}: missing {', '.join(missing)}: cannot build the geometry without "
                            f"{'them' if len(missing) > 1 else 'it'}")
    n = int(ds.NumberOfFrames)
    incr = {}
    for name in ("PositionerPrimaryAngleIncrement", "PositionerSecondaryAngleIncrement"):
        values = np.atleast_1d(np.asarray(ds.get(name, [0.0] * n), dtype=float))
        if values.size == 1 and n > 1 and name not in ds:
            values = np.zeros(n)
        if values.size != n:
            raise ScanFileError(f"{path}: {name} has {values.size} values for {n} frames")
        incr[name] = values
    sdd, sad = float(ds.DistanceSourceToDetector), float(ds.DistanceSourceToPatient)
    if not sdd > sad > 0:
        raise ScanFileError(f"{path}: DistanceSourceToDetector ({sdd}) must exceed DistanceSourceToPatient ({sad}) > 0")
    spacing = [float(v) for v in ds.ImagerPixelSpacing]
    if len(spacing) != 2 or min(spacing) <= 0:
        raise ScanFileError(f"{path}: ImagerPixelSpacing must be two positive numbers, got {spacing}")
    frames = ds.pixel_array.reshape(n, int(ds.Rows), int(ds.Columns))
    return {"path": path, "frames": frames, "sad": sad, "sdd": sdd, "pitch": (spacing[1], spacing[0]),
            "primary": float(ds.PositionerPrimaryAngle) + incr["PositionerPrimaryAngleIncrement"],
            "secondary": float(ds.PositionerSecondaryAngle) + incr["PositionerSecondaryAngleIncrement"],
            "eta": math.radians(float(ds.get("FieldOfViewRotation", 0.0) or 0.0)),
            "when": str(ds.get("AcquisitionDateTime", "")) or str(ds.get("AcquisitionTime", "")),
            "frame_time_s": float(ds.get("FrameTime", 0.0) or 0.0) / 1000.0}


def import_xa(files: Sequence[str | Path], out: str | Path, *, overwrite: bool = False) -> Path:
    """One or more XA runs of one orbit (ordered by acquisition time) as the scan file ``out``."""
    paths = [Path(p) for p in files]
    if not paths:
        raise ScanFileError("no DICOM files given")
    runs = sorted((_run(p) for p in paths), key=lambda r: r["when"])
    first = runs[0]
    for r in runs[1:]:
        for key in ("sad", "sdd", "pitch"):
            if not np.allclose(r[key], first[key], rtol=1e-6):
                raise ScanFileError(f"{r['path']}: {key} {r[key]} differs from {first['path']}'s {first[key]}: "
                                    "runs of one orbit share the C-arm's distances and detector")
        if r["frames"].shape[1:] != first["frames"].shape[1:]:
            raise ScanFileError(f"{r['path']}: frames of {r['frames'].shape[1:]} px, the first run has "
                                f"{first['frames'].shape[1:]}")
    rows, cols = first["frames"].shape[1:]
    panel = Panel(rows, cols, first["pitch"][0], first["pitch"][1])
    primary = np.concatenate([r["primary"] for r in runs])
    secondary = np.concatenate([r["secondary"] for r in runs])
    frames = np.concatenate([r["frames"] for r in runs])
    geometry = ViewGeometry.from_carm(np.radians(primary), np.radians(secondary), first["sad"], first["sdd"], panel,
                                      eta=first["eta"])
    bright = float(np.percentile(frames, 99.9))
    assumptions = ["no dark or flat frames in an XA run: one dark of 0 and one flat at the run's bright level "
                   f"({bright:.10g}, the 99.9th percentile) were added",
                   "principal point at the detector centre (XA does not record it)",
                   "angles: primary = LAO/RAO = rotation theta, secondary = CRAN/CAUD = tilt phi; increments are "
                   "offsets from the first frame's angle"]
    dtype = "uint16" if frames.dtype.kind == "u" and frames.dtype.itemsize <= 2 else "float32"
    with ScanWriter(out, panel, frame_dtype=dtype, axes=AXES, orbit_name="dicom-xa",
                    orbit_params={"runs": len(runs), "files": [p.name for p in paths]}, overwrite=overwrite) as w:
        w.append(np.zeros((rows, cols), dtype=dtype), ImageKey.DARK, 0.0)
        w.append(np.full((rows, cols), bright, dtype=dtype), ImageKey.FLAT, 0.0)
        t = 0.0
        for i in range(frames.shape[0]):
            angles = {"carm.primary": float(primary[i]), "carm.secondary": float(secondary[i])}
            w.append(frames[i].astype(dtype, copy=False), ImageKey.PROJECTION, t, nominal_vector=geometry.vectors[i],
                     encoders=angles, commanded=angles, flush=False)
            t += first["frame_time_s"]
        w.set_attrs("provenance", imported_from="DICOM XA", import_assumptions_json={"assumed": assumptions})
    return Path(out)
