"""C-arm runs as DICOM X-ray angiography (XA) multi-frame objects, both ways (pydicom encodes and decodes).

``write_xa_run`` writes a C-arm scan's projections as one object, as a C-arm's own export does: classic XA or
XRF (the positioner angles of the first frame and, per frame, their increments from it; source-to-detector and
source-to-isocenter distances; imager pixel spacing) or Enhanced XA (the same per frame in functional groups).
``import_xa`` reads one or more such runs of one orbit (in acquisition order) into a scan file with the nominal
geometry those attributes give, and records what it had to assume (no darks and flats in an XA run: dark 0, flat the run's bright level; the principal point
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

from orbitct.geometry import Panel, ViewGeometry
from orbitct.scanfile._xa_angles import ANGLE_INCREMENTS, AngleIncrements, AngleReadingError, frame_angles
from orbitct.scanfile._xa_objects import RUN_KINDS, Run, RunKind, classic, enhanced
from orbitct.scanfile.errors import ScanFileError
from orbitct.scanfile.keys import ImageKey
from orbitct.scanfile.reader import ScanFile
from orbitct.scanfile.writer import ScanWriter

PATIENT_SIDES_UNKNOWN = (
    "left and right relative to the patient are not established: frames are read with columns "
    "along u and rows along v (PatientOrientation not read), and a reconstruction may be the "
    "patient's mirror image; check against a marker (docs/geometry.md)"
)


def patient_sides_caveat(assumptions: Sequence[str]) -> str:
    """The caveat a volume reconstructed from an imported run carries ('' when the scan was not imported)."""
    return (
        f"reconstructed from an imported C-arm run: {PATIENT_SIDES_UNKNOWN}"
        if PATIENT_SIDES_UNKNOWN in assumptions
        else ""
    )


__all__ = ["ANGLE_INCREMENTS", "AngleIncrements", "import_xa", "patient_sides_caveat", "write_xa_run"]

AXES = {"carm.primary": "deg", "carm.secondary": "deg"}
REQUIRED = ("NumberOfFrames", "Rows", "Columns", "PixelData")
CLASSIC_REQUIRED = (
    "PositionerPrimaryAngle",
    "PositionerSecondaryAngle",
    "DistanceSourceToDetector",
    "DistanceSourceToPatient",
    "ImagerPixelSpacing",
)


def write_xa_run(
    scan: str | Path,
    out: str | Path,
    *,
    patient_id: str = "",
    part: tuple[int, int] | None = None,
    kind: RunKind = "xa",
) -> Path:
    """Write the projections of C-arm scan ``scan`` (projections ``part[0]:part[1]`` only, when given: one run of an
    orbit acquired as several) as one multi-frame object ``out``: classic XA, XRF, or Enhanced XA."""
    if kind not in RUN_KINDS:
        raise ScanFileError(f"run kind {kind!r}: allowed are {', '.join(RUN_KINDS)}")
    with ScanFile(scan) as sf:
        proj = sf.projection_indices
        if part is not None:
            proj = proj[part[0] : part[1]]
        if proj.size == 0:
            raise ScanFileError(f"{scan}: no projection frames to export")
        angles = {}
        for axis in AXES:
            read, cmd = sf.axes("encoders").get(axis), sf.axes("commanded").get(axis)
            if read is None:
                if cmd is None:
                    raise ScanFileError(f"{scan}: no {axis} positions: XA export is for C-arm scans")
                value = cmd
            else:
                value = read if cmd is None else np.where(np.isfinite(read), read, cmd)
            angles[axis] = value[proj]
        nominal = sf.geometry("nominal")[proj]
        frames = np.asarray(sf.frames[proj.tolist()], dtype=np.uint16)
        pitch_col, pitch_row = sf.panel.pitch_mm
        times = sf.time_s[proj]
        exposure = (sf.attrs_json("provenance", "config_json") or {}).get("exposure") or {}
    run = Run(
        frames=frames,
        primary_deg=angles["carm.primary"],
        secondary_deg=angles["carm.secondary"],
        sad_mm=float(np.median(nominal.sod())),
        sdd_mm=float(np.median(nominal.sdd)),
        pitch_row_mm=pitch_row,
        pitch_col_mm=pitch_col,
        times_s=np.nan_to_num(times),
        patient_id=patient_id or Path(scan).stem[:64],
        kv=exposure.get("kv"),
        ma=exposure.get("ma"),
        exposure_ms=exposure.get("exposure_ms"),
    )
    start = dt.datetime.now() + dt.timedelta(seconds=float(run.times_s[0]))
    ds = enhanced(run, start) if kind == "enhanced-xa" else classic(run, kind, start)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    ds.save_as(out, enforce_file_format=True)
    return out


def _number(path: Path, where: Any, name: str) -> float:
    """Attribute ``name`` of dataset ``where`` as a float, or ScanFileError naming it."""
    value: Any = where.get(name) if where is not None else None
    if value is None or value == "":
        raise ScanFileError(f"{path}: missing {name}: cannot build the geometry without it")
    try:
        return float(value)
    except (TypeError, ValueError):
        raise ScanFileError(f"{path}: {name} is {value!r}, expected a number") from None


def _numbers(path: Path, where: Any, name: str) -> list[float]:
    """A multi-valued number attribute as floats, or ScanFileError naming it."""
    value: Any = where.get(name) if where is not None else None
    try:
        return [
            float(v)
            for v in (
                value
                if isinstance(value, (list, tuple))
                or (hasattr(value, "__iter__") and not isinstance(value, (str, bytes)))
                else [value]
            )
        ]
    except (TypeError, ValueError):
        raise ScanFileError(f"{path}: {name} is {value!r}, expected numbers") from None


def _macro(ds: Any, frame: int, sequence: str) -> Any:
    """The item of functional group ``sequence`` for ``frame``: its own, else the shared one, else None."""
    own, shared = ds.get("PerFrameFunctionalGroupsSequence") or [], ds.get("SharedFunctionalGroupsSequence") or []
    for group in ([own[frame]] if frame < len(own) else []) + list(shared[:1]):
        if sequence in group and len(group[sequence].value):
            return group[sequence].value[0]
    return None


def _required_macro(path: Path, ds: Any, frame: int, sequence: str, group: str) -> Any:
    item = _macro(ds, frame, sequence)
    if item is None:
        raise ScanFileError(
            f"{path}: frame {frame + 1} has no {sequence} (the {group} functional group, neither its "
            "own nor shared): cannot build its geometry"
        )
    return item


def _enhanced_geometry(path: Path, ds: Any, n: int) -> dict[str, Any]:
    """Angles, distances, pixel spacing and field-of-view rotation from an Enhanced XA's functional groups."""
    per_frame = ds.get("PerFrameFunctionalGroupsSequence")
    if per_frame is None or len(per_frame) != n:
        raise ScanFileError(
            f"{path}: PerFrameFunctionalGroupsSequence has {0 if per_frame is None else len(per_frame)} "
            f"items for {n} frames"
        )
    primary, secondary, sad, sdd, spacing, rotation, times = [], [], set(), set(), set(), set(), []
    for i in range(n):
        positioner = _required_macro(path, ds, i, "PositionerPositionSequence", "X-Ray Positioner")
        primary.append(_number(path, positioner, "PositionerPrimaryAngle"))
        secondary.append(_number(path, positioner, "PositionerSecondaryAngle"))
        geometry = _required_macro(path, ds, i, "XRayGeometrySequence", "X-Ray Geometry")
        sad.add(_number(path, geometry, "DistanceSourceToIsocenter"))
        sdd.add(_number(path, geometry, "DistanceSourceToDetector"))
        pixels = _macro(ds, i, "FramePixelDataPropertiesSequence")
        if pixels is None or "ImagerPixelSpacing" not in pixels:
            raise ScanFileError(f"{path}: frame {i + 1}: missing ImagerPixelSpacing (FramePixelDataPropertiesSequence)")
        spacing.add(tuple(_numbers(path, pixels, "ImagerPixelSpacing")))
        _linear(path, pixels)
        view = _macro(ds, i, "FieldOfViewSequence")
        rotation.add(float(view.get("FieldOfViewRotation", 0.0) or 0.0) if view is not None else 0.0)
        content = _macro(ds, i, "FrameContentSequence")
        times.append(str(content.get("FrameAcquisitionDateTime", "")) if content is not None else "")
    for name, values in (
        ("DistanceSourceToIsocenter", sad),
        ("DistanceSourceToDetector", sdd),
        ("ImagerPixelSpacing", spacing),
        ("FieldOfViewRotation", rotation),
    ):
        if len(values) > 1:
            raise ScanFileError(
                f"{path}: {name} changes between frames ({sorted(values)[:3]}...): a run with a "
                "moving detector or changing distances is not supported"
            )
    seconds = [_seconds(t) for t in times]
    known = [s for s in seconds if s is not None]
    frame_time_s = float(np.median(np.diff(known))) if n > 1 and len(known) == len(seconds) else 0.0
    return {
        "primary": np.array(primary),
        "secondary": np.array(secondary),
        "sad": sad.pop(),
        "sdd": sdd.pop(),
        "spacing": list(spacing.pop()),
        "rotation_deg": rotation.pop(),
        "frame_time_s": frame_time_s,
    }


def _seconds(stamp: str) -> float | None:
    """A DICOM date-time (DT) in seconds, None when absent or unreadable."""
    from pydicom.valuerep import DT

    try:
        return DT(stamp).timestamp() if stamp else None
    except ValueError:
        return None


def _linear(path: Path, where: Any) -> None:
    """Refuse pixel data that are not proportional to the detected intensity (line integrals need that)."""
    relation = str(where.get("PixelIntensityRelationship", "LIN") or "LIN")
    if relation != "LIN":
        raise ScanFileError(
            f"{path}: PixelIntensityRelationship is {relation}; only LIN (raw, proportional to the "
            "X-ray intensity) can be turned into line integrals without the vendor's LUT"
        )


def _require(path: Path, ds: Any, names: Sequence[str]) -> None:
    missing = [k for k in names if k not in ds or (k != "PixelData" and ds.get(k) in (None, ""))]
    if missing == ["PixelData"]:
        raise ScanFileError(f"{path}: missing PixelData: the run holds no images")
    if missing:
        raise ScanFileError(
            f"{path}: missing {', '.join(missing)}: cannot build the geometry without "
            f"{'them' if len(missing) > 1 else 'it'}"
        )


def _classic_geometry(path: Path, ds: Any, n: int, choice: AngleIncrements) -> dict[str, Any]:
    """Angles (first frame plus increments, read as ``choice``), distances and pixel spacing of a classic XA or XRF
    object."""
    _require(path, ds, CLASSIC_REQUIRED)
    _linear(path, ds)
    incr = []
    for name in ("PositionerPrimaryAngleIncrement", "PositionerSecondaryAngleIncrement"):
        try:
            values = np.atleast_1d(np.asarray(ds.get(name), dtype=float)) if name in ds else np.zeros(1)
        except (TypeError, ValueError):
            raise ScanFileError(f"{path}: {name} holds something other than numbers") from None
        if values.size not in (1, n):
            raise ScanFileError(f"{path}: {name} has {values.size} values for {n} frames (DICOM allows 1 or {n})")
        incr.append(values)
    start = (_number(path, ds, "PositionerPrimaryAngle"), _number(path, ds, "PositionerSecondaryAngle"))
    try:
        angles = frame_angles(start, (incr[0], incr[1]), n, choice)
    except AngleReadingError as exc:
        raise ScanFileError(f"{path}: {exc}") from None
    return {
        "primary": angles.primary_deg,
        "secondary": angles.secondary_deg,
        "increments": f"{path.name}: PositionerPrimary/SecondaryAngleIncrement {angles.why}",
        "sad": _number(path, ds, "DistanceSourceToPatient"),
        "sdd": _number(path, ds, "DistanceSourceToDetector"),
        "spacing": _numbers(path, ds, "ImagerPixelSpacing"),
        "rotation_deg": float(ds.get("FieldOfViewRotation", 0.0) or 0.0),
        "frame_time_s": float(ds.get("FrameTime", 0.0) or 0.0) / 1000.0,
    }


#: the storage classes of X-ray runs that hold an orbit (classic and enhanced XA and XRF)
XRAY_RUN_CLASSES = {
    "1.2.840.10008.5.1.4.1.1.12.1": "X-Ray Angiographic Image Storage",
    "1.2.840.10008.5.1.4.1.1.12.1.1": "Enhanced XA Image Storage",
    "1.2.840.10008.5.1.4.1.1.12.2": "X-Ray Radiofluoroscopic Image Storage",
    "1.2.840.10008.5.1.4.1.1.12.2.1": "Enhanced XRF Image Storage",
}
MAX_SIDE_PX = 16384  # rows or columns beyond this are no X-ray panel's


def _count(path: Path, ds: Any, name: str, most: int) -> int:
    """A whole-number attribute between 1 and ``most``, or ScanFileError saying what it holds."""
    value = ds.get(name)
    try:
        number = int(value)
        whole = float(value) == number
    except (TypeError, ValueError, OverflowError):
        whole = False
    if not whole or not 1 <= number <= most:
        raise ScanFileError(f"{path}: {name} is {value!r}; an X-ray run has 1 to {most} there")
    return number


def _header(path: Path) -> Any:
    """The DICOM object at ``path`` read without its pixels, checked to be an X-ray run whose pixels can be read here:
    its storage class, one monochrome sample per pixel, sizes that are possible and fit this machine, pixel data as
    long as the sizes say. Nothing of the pixels is read before these checks."""
    import psutil
    import pydicom
    from pydicom.uid import UID

    try:
        ds = pydicom.dcmread(path, defer_size=4096)  # large values (the pixels) are read when used, not now
    except Exception as exc:  # noqa: BLE001 - any unreadable file is named with the reason
        why = str(exc).splitlines()[0][:200] if str(exc) else "its header cannot be parsed"
        raise ScanFileError(f"{path}: not a readable DICOM file ({why})") from None
    sop = str(ds.get("SOPClassUID", "") or "")
    if sop and sop not in XRAY_RUN_CLASSES:
        name = UID(sop).name if UID(sop).is_valid else sop
        raise ScanFileError(
            f"{path}: a DICOM object of the class {name} ({sop}), not an X-ray angiography or "
            "fluoroscopy run (XA or XRF, classic or enhanced): it holds no orbit to import"
        )
    if ds.get("Modality") not in ("XA", "RF"):
        raise ScanFileError(f"{path}: modality {ds.get('Modality')!r}, expected an XA (or XRF) run")
    _require(path, ds, REQUIRED)
    n = _count(path, ds, "NumberOfFrames", 1_000_000)
    rows, cols = _count(path, ds, "Rows", MAX_SIDE_PX), _count(path, ds, "Columns", MAX_SIDE_PX)
    samples = ds.get("SamplesPerPixel", 1)
    photometric = str(ds.get("PhotometricInterpretation", "MONOCHROME2") or "")
    if samples != 1 or not photometric.startswith("MONOCHROME"):
        raise ScanFileError(
            f"{path}: {photometric or 'colour'} pixels (SamplesPerPixel {samples}); an X-ray run is "
            "monochrome, one sample per pixel"
        )
    bits = int(ds.get("BitsAllocated", 16) or 0)
    if bits not in (8, 16, 32):
        raise ScanFileError(f"{path}: BitsAllocated is {bits}; an X-ray run stores 8, 16 or 32 bits a pixel")
    need = n * rows * cols * 8  # the run as float64 while it is imported
    available = psutil.virtual_memory().available
    if need > available // 2:
        raise ScanFileError(
            f"{path}: {n} frames of {rows} x {cols} pixels need about {need / 2**30:.1f} GiB to import "
            f"and {available / 2**30:.1f} GiB is available; import it in parts (orbitct export xa "
            "--frames on the writing side) or on a larger machine"
        )
    element = ds.get_item("PixelData", keep_deferred=True)  # its length, not its value
    stored = getattr(element, "length", None)
    expected = n * rows * cols * bits // 8
    if not ds.file_meta.TransferSyntaxUID.is_compressed and stored is not None and 0 <= stored < expected:
        raise ScanFileError(
            f"{path}: the pixel data hold {stored} bytes, {n} frames of {rows} x {cols} at {bits} bits "
            f"need {expected}: the file is cut short or its sizes are wrong"
        )
    return ds


def _finite_numbers(path: Path, found: dict[str, Any]) -> None:
    """Angles, distances and spacing are numbers (not NaN or infinite)."""
    for key, name in (
        ("primary", "the primary angles"),
        ("secondary", "the secondary angles"),
        ("sad", "the source-to-isocenter distance"),
        ("sdd", "DistanceSourceToDetector"),
        ("spacing", "ImagerPixelSpacing"),
        ("rotation_deg", "FieldOfViewRotation"),
    ):
        if not np.isfinite(np.asarray(found[key], dtype=float)).all():
            raise ScanFileError(f"{path}: {name}: a value is not a finite number (NaN or infinite)")


def _run(path: Path, choice: AngleIncrements) -> dict[str, Any]:
    """The geometry-relevant content of one XA/XRF run (classic or enhanced), or ScanFileError naming what is missing
    or wrong; the header is checked before a pixel is read."""
    ds = _header(path)
    n = int(ds.NumberOfFrames)
    is_enhanced = "PerFrameFunctionalGroupsSequence" in ds or "SharedFunctionalGroupsSequence" in ds
    found = _enhanced_geometry(path, ds, n) if is_enhanced else _classic_geometry(path, ds, n, choice)
    _finite_numbers(path, found)
    _moves_if_dynamic(path, ds, found, n)
    sdd, sad, spacing = found["sdd"], found["sad"], found["spacing"]
    distance = "DistanceSourceToIsocenter" if is_enhanced else "DistanceSourceToPatient"
    if not sdd > sad > 0:
        raise ScanFileError(f"{path}: DistanceSourceToDetector ({sdd}) must exceed {distance} ({sad}) > 0")
    if len(spacing) != 2 or min(spacing) <= 0:
        raise ScanFileError(f"{path}: ImagerPixelSpacing must be two positive numbers, got {spacing}")
    try:
        frames = np.asarray(ds.pixel_array).reshape(n, int(ds.Rows), int(ds.Columns))
    except Exception as exc:  # noqa: BLE001 - a decoder's failure, or pixels that do not match the header
        text = str(exc).splitlines()[0][:200].rstrip(":") if str(exc) else "they do not match the header"
        syntax = ds.file_meta.TransferSyntaxUID
        raise ScanFileError(f"{path}: its pixel data ({syntax.name}) cannot be read: {text}") from None
    return {
        "path": path,
        "frames": frames,
        "sad": sad,
        "sdd": sdd,
        "pitch": (spacing[1], spacing[0]),
        "primary": found["primary"],
        "secondary": found["secondary"],
        "eta": math.radians(found["rotation_deg"]),
        "when": str(ds.get("AcquisitionDateTime", "")) or str(ds.get("AcquisitionTime", "")),
        "frame_time_s": found["frame_time_s"],
        "kind": "Enhanced XA" if is_enhanced else ("XRF" if ds.Modality == "RF" else "XA"),
        "increments": found.get("increments", ""),
    }


STILL_DEG = 0.5  # frames within this of one angle stand still
STILL_SHARE = 0.9  # a DYNAMIC run with this share of its frames standing still did not move


def _moves_if_dynamic(path: Path, ds: Any, found: dict[str, Any], n: int) -> None:
    """Refuse a run that says the C-arm moved (PositionerMotion DYNAMIC) whose frames nearly all stand at one angle."""
    if str(ds.get("PositionerMotion", "") or "") != "DYNAMIC" or n < 2:
        return
    angles = np.stack([found["primary"], found["secondary"]], axis=1)
    centre = np.median(angles, axis=0)
    still = int(np.sum(np.linalg.norm(angles - centre, axis=1) <= STILL_DEG))
    if still >= STILL_SHARE * n:
        raise ScanFileError(
            f"{path}: PositionerMotion is DYNAMIC but {still} of its {n} frames stand within {STILL_DEG} deg of "
            f"({centre[0]:.4g}, {centre[1]:.4g}) deg: the per-frame angles are missing or were read wrongly; for a "
            "classic run choose how its angle increments are stored (--angle-increments offsets, steps or absolute)"
        )


def import_xa(
    files: Sequence[str | Path], out: str | Path, *, overwrite: bool = False, angle_increments: AngleIncrements = "auto"
) -> Path:
    """One or more XA runs of one orbit (ordered by acquisition time) as the scan file ``out``; a classic run's angle
    increments read as ``angle_increments`` (offsets, steps or absolute angles) or, with "auto", as their values show."""
    paths = [Path(p) for p in files]
    if not paths:
        raise ScanFileError("no DICOM files given")
    runs = sorted((_run(p, angle_increments) for p in paths), key=lambda r: r["when"])
    first = runs[0]
    for r in runs[1:]:
        for key in ("sad", "sdd", "pitch", "eta"):
            if not np.allclose(r[key], first[key], rtol=1e-6):
                raise ScanFileError(
                    f"{r['path']}: {key} {r[key]} differs from {first['path']}'s {first[key]}: "
                    "runs of one orbit share the C-arm's distances and detector"
                )
        if r["frames"].shape[1:] != first["frames"].shape[1:]:
            raise ScanFileError(
                f"{r['path']}: frames of {r['frames'].shape[1:]} px, the first run has {first['frames'].shape[1:]}"
            )
    rows, cols = first["frames"].shape[1:]
    panel = Panel(rows, cols, first["pitch"][0], first["pitch"][1])
    primary = np.concatenate([r["primary"] for r in runs])
    secondary = np.concatenate([r["secondary"] for r in runs])
    frames = np.concatenate([r["frames"] for r in runs])
    geometry = ViewGeometry.from_carm(
        np.radians(primary), np.radians(secondary), first["sad"], first["sdd"], panel, eta=first["eta"]
    )
    bright = float(np.percentile(frames, 99.9))
    assumptions = [
        "no dark or flat frames in an XA run: one dark of 0 and one flat at the run's bright level "
        f"({bright:.10g}, the 99.9th percentile) were added",
        "principal point at the detector centre (XA does not record it)",
        "pixel data raw (PixelIntensityRelationship LIN): line integrals are -log(frame / flat)",
        "angles: primary = LAO/RAO = rotation theta, secondary = CRAN/CAUD = tilt phi",
        PATIENT_SIDES_UNKNOWN,
    ]
    kinds = sorted({r["kind"] for r in runs})
    if "Enhanced XA" in kinds:
        assumptions.append(
            "Enhanced XA: each frame's angles from its X-Ray Positioner functional group, distances "
            "from X-Ray Geometry (source to isocenter, source to detector), pixel spacing from X-Ray "
            "Frame Pixel Data Properties, detector rotation from Field of View"
        )
    if {"XA", "XRF"} & set(kinds):
        assumptions.append(
            "classic XA/XRF: per-frame angles from the first frame's angles and the increments; "
            "DistanceSourceToPatient is the source-to-isocenter distance"
        )
        assumptions += [r["increments"] for r in runs if r["increments"]]
    dtype = "uint16" if frames.dtype.kind == "u" and frames.dtype.itemsize <= 2 else "float32"
    with ScanWriter(
        out,
        panel,
        frame_dtype=dtype,
        axes=AXES,
        orbit_name="dicom-xa",
        orbit_params={"runs": len(runs), "files": [p.name for p in paths]},
        overwrite=overwrite,
    ) as w:
        w.append(np.zeros((rows, cols), dtype=dtype), ImageKey.DARK, 0.0)
        w.append(np.full((rows, cols), bright, dtype=dtype), ImageKey.FLAT, 0.0)
        t = 0.0
        for i in range(frames.shape[0]):
            angles = {"carm.primary": float(primary[i]), "carm.secondary": float(secondary[i])}
            w.append(
                frames[i].astype(dtype, copy=False),
                ImageKey.PROJECTION,
                t,
                nominal_vector=geometry.vectors[i],
                encoders=angles,
                commanded=angles,
                flush=False,
            )
            t += first["frame_time_s"]
        w.set_attrs(
            "provenance", imported_from="DICOM " + " + ".join(kinds), import_assumptions_json={"assumed": assumptions}
        )
    return Path(out)
