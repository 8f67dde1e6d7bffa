"""The DICOM objects a C-arm run leaves the machine as (pydicom encodes them): classic XA, XRF, and Enhanced XA with
its per-frame functional groups. ``xa.write_xa_run`` gathers a ``Run`` from a scan file and picks the kind."""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from orbitct.dicom import ENTIRE_BODY, new_instance, sequence_item
from orbitct.scanfile.errors import ScanFileError

RunKind = Literal["xa", "xrf", "enhanced-xa"]
RUN_KINDS: tuple[str, ...] = ("xa", "xrf", "enhanced-xa")


@dataclass(frozen=True)
class Run:
    """One run's frames and what a C-arm records about them (angles in degrees, distances and pitch in mm)."""

    frames: np.ndarray  # (n, rows, cols) uint16
    primary_deg: np.ndarray
    secondary_deg: np.ndarray
    sad_mm: float
    sdd_mm: float
    pitch_row_mm: float
    pitch_col_mm: float
    times_s: np.ndarray
    patient_id: str
    kv: float | None = None  # the technique, where the scan recorded it
    ma: float | None = None
    exposure_ms: float | None = None


def _num(value: float) -> str:
    return f"{value:.10g}"


def _common(ds: Any, run: Run, modality: str, manufacturer: str, start: dt.datetime) -> None:
    """Patient, study, series, equipment and pixel description shared by every kind."""
    from pydicom.uid import generate_uid

    ds.Modality, ds.Manufacturer = modality, manufacturer
    ds.PatientName, ds.PatientID, ds.PatientBirthDate, ds.PatientSex = "", run.patient_id, "", ""
    ds.StudyInstanceUID, ds.SeriesInstanceUID = generate_uid(), generate_uid()
    ds.StudyDate = ds.SeriesDate = ds.ContentDate = start.strftime("%Y%m%d")
    ds.StudyTime = ds.SeriesTime = ds.ContentTime = start.strftime("%H%M%S")
    ds.AcquisitionDateTime = start.strftime("%Y%m%d%H%M%S.%f")
    ds.StudyID, ds.SeriesNumber, ds.InstanceNumber, ds.AccessionNumber, ds.ReferringPhysicianName = "1", 1, 1, "", ""
    ds.NumberOfFrames = int(run.frames.shape[0])
    ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
    ds.Rows, ds.Columns = int(run.frames.shape[1]), int(run.frames.shape[2])
    ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 0
    ds.PixelData = np.ascontiguousarray(run.frames, dtype=np.uint16).tobytes()


def classic(run: Run, kind: Literal["xa", "xrf"], start: dt.datetime) -> Any:
    """A classic multi-frame XA (or XRF) object: first-frame angles plus per-frame increments."""
    from pydicom.uid import (
        XRayAngiographicImageStorage,
        XRayRadiofluoroscopicImageStorage,
    )

    ds = new_instance(XRayAngiographicImageStorage if kind == "xa" else XRayRadiofluoroscopicImageStorage)
    _common(ds, run, "XA" if kind == "xa" else "RF", "orbitct C-arm twin", start)
    ds.AcquisitionDate = ds.ContentDate
    ds.ImageType = ["ORIGINAL", "PRIMARY", "SINGLE PLANE"]
    ds.PixelIntensityRelationship = "LIN"
    ds.PatientOrientation, ds.Laterality, ds.RadiationSetting = "", "", "GR"
    ds.KVP = _num(run.kv) if run.kv is not None else ""
    ds.XRayTubeCurrent, ds.ExposureTime, ds.Exposure = "", "", ""  # integers; the exact values follow
    _technique(ds, run)
    ds.PositionerMotion = "DYNAMIC"
    ds.PositionerPrimaryAngle, ds.PositionerSecondaryAngle = _num(run.primary_deg[0]), _num(run.secondary_deg[0])
    ds.PositionerPrimaryAngleIncrement = [_num(a) for a in run.primary_deg - run.primary_deg[0]]
    ds.PositionerSecondaryAngleIncrement = [_num(a) for a in run.secondary_deg - run.secondary_deg[0]]
    ds.DistanceSourceToDetector, ds.DistanceSourceToPatient = _num(run.sdd_mm), _num(run.sad_mm)
    ds.ImagerPixelSpacing = [_num(run.pitch_row_mm), _num(run.pitch_col_mm)]  # row spacing, column spacing
    ds.FrameTime = _num(1000.0 * float(np.median(np.diff(run.times_s))) if run.times_s.size > 1 else 0.0)
    ds.FrameIncrementPointer = (0x0018, 0x1063)
    return ds


def _technique(ds: Any, run: Run) -> None:
    """The X-ray technique in the floating-point attributes, where the scan recorded it."""
    if run.ma is not None:
        ds.XRayTubeCurrentInuA = _num(1000.0 * run.ma)
    if run.exposure_ms is not None:
        ds.ExposureTimeInuS = _num(1000.0 * run.exposure_ms)
    if run.ma is not None and run.exposure_ms is not None:
        ds.ExposureInuAs = round(run.ma * run.exposure_ms)


def enhanced(run: Run, start: dt.datetime) -> Any:
    """An Enhanced XA object: what is the same for every frame in the shared functional groups (distances,
    pixel spacing, field of view, the irradiation event), each frame's angles and time in its own."""
    from pydicom.sequence import Sequence
    from pydicom.uid import EnhancedXAImageStorage, generate_uid

    n = int(run.frames.shape[0])
    ds = new_instance(EnhancedXAImageStorage)
    _common(ds, run, "XA", "orbitct C-arm twin", start)
    ds.ManufacturerModelName, ds.DeviceSerialNumber, ds.SoftwareVersions = "C-arm twin", "0", "orbitct"
    ds.ImageType = ["ORIGINAL", "PRIMARY", "SINGLE PLANE", "NONE"]
    ds.PlanesInAcquisition, ds.PlaneIdentification = "MONOPLANE", "MONOPLANE"
    ds.ContentQualification, ds.BurnedInAnnotation, ds.LossyImageCompression = "PRODUCT", "NO", "00"
    ds.RecognizableVisualFeatures = "NO"
    ds.PresentationLUTShape = "IDENTITY"
    ds.AcquisitionDuration = float(run.times_s[-1] - run.times_s[0]) if n > 1 else 0.0
    ds.AcquisitionContextSequence = Sequence()
    # XA/XRF acquisition: the technique is mandatory here
    if run.kv is None or run.ma is None or run.exposure_ms is None:
        raise ScanFileError(
            "Enhanced XA needs the X-ray technique (kV, mA, exposure time); the scan records none: "
            "export it as classic XA"
        )
    ds.RadiationSetting, ds.RadiationMode, ds.KVP = "GR", "PULSED", _num(run.kv)
    ds.XRayTubeCurrentInmA, ds.ExposureTimeInms = float(run.ma), float(run.exposure_ms)  # (not mAs as well)
    ds.AveragePulseWidth = float(run.exposure_ms)
    ds.DistanceReceptorPlaneToDetectorHousing, ds.AcquiredImageAreaDoseProduct = None, None
    ds.PositionerType, ds.CArmPositionerTabletopRelationship = "CARM", "NO"
    ds.AcquisitionProtocolName = "orbitct rotational run"
    # the dimensions: frames in acquisition order
    dim_uid = generate_uid()
    ds.DimensionOrganizationSequence = Sequence([sequence_item(DimensionOrganizationUID=dim_uid)])
    ds.DimensionIndexSequence = Sequence(
        [
            sequence_item(
                DimensionOrganizationUID=dim_uid,
                DimensionIndexPointer=0x00209128,
                FunctionalGroupPointer=0x00209111,
                DimensionDescriptionLabel="Temporal position",
            )
        ]
    )
    shared = sequence_item(
        XRayGeometrySequence=Sequence(
            [sequence_item(DistanceSourceToIsocenter=run.sad_mm, DistanceSourceToDetector=run.sdd_mm)]
        ),
        FramePixelDataPropertiesSequence=Sequence(
            [
                sequence_item(
                    FrameType=["ORIGINAL", "PRIMARY", "SINGLE PLANE", "NONE"],
                    ImagerPixelSpacing=[run.pitch_row_mm, run.pitch_col_mm],
                    PixelIntensityRelationship="LIN",
                    PixelIntensityRelationshipSign=1,
                    GeometricalProperties="UNIFORM",
                    ImageProcessingApplied="NONE",
                )
            ]
        ),
        FieldOfViewSequence=Sequence(
            [
                sequence_item(
                    FieldOfViewShape="RECTANGLE",
                    FieldOfViewDimensionsInFloat=[run.pitch_row_mm * ds.Rows, run.pitch_col_mm * ds.Columns],
                    FieldOfViewOrigin=[0.0, 0.0],
                    FieldOfViewRotation="0",
                    FieldOfViewHorizontalFlip="NO",
                )
            ]
        ),
        FrameVOILUTSequence=Sequence(
            [
                sequence_item(
                    WindowCenter=float(np.percentile(run.frames, 50)), WindowWidth=max(1.0, float(np.ptp(run.frames)))
                )
            ]
        ),
        TablePositionSequence=Sequence(
            [
                sequence_item(  # the twin has no table: at its reference position
                    TableTopVerticalPosition=0.0,
                    TableTopLongitudinalPosition=0.0,
                    TableTopLateralPosition=0.0,
                    TableHorizontalRotationAngle=0.0,
                    TableHeadTiltAngle=0.0,
                    TableCradleTiltAngle=0.0,
                )
            ]
        ),
        CollimatorShapeSequence=Sequence(
            [
                sequence_item(  # open: the whole panel
                    CollimatorShape="RECTANGULAR",
                    CollimatorLeftVerticalEdge=0,
                    CollimatorRightVerticalEdge=int(ds.Columns),
                    CollimatorUpperHorizontalEdge=0,
                    CollimatorLowerHorizontalEdge=int(ds.Rows),
                )
            ]
        ),
        FrameAcquisitionSequence=Sequence([sequence_item(KVP=_num(run.kv), XRayTubeCurrentInmA=float(run.ma))]),
        IrradiationEventIdentificationSequence=Sequence([sequence_item(IrradiationEventUID=generate_uid())]),
        FrameAnatomySequence=Sequence(
            [sequence_item(FrameLaterality="U", AnatomicRegionSequence=Sequence([sequence_item(**ENTIRE_BODY)]))]
        ),
    )
    ds.SharedFunctionalGroupsSequence = Sequence([shared])
    frames = []
    for i in range(n):
        when = start + dt.timedelta(seconds=float(run.times_s[i] - run.times_s[0]))
        frames.append(
            sequence_item(
                FrameContentSequence=Sequence(
                    [
                        sequence_item(
                            FrameAcquisitionDateTime=when.strftime("%Y%m%d%H%M%S.%f"),
                            FrameReferenceDateTime=when.strftime("%Y%m%d%H%M%S.%f"),
                            FrameAcquisitionDuration=float(run.exposure_ms),
                            TemporalPositionIndex=i + 1,
                            DimensionIndexValues=[i + 1],
                        )
                    ]
                ),
                PositionerPositionSequence=Sequence(
                    [
                        sequence_item(
                            PositionerPrimaryAngle=float(run.primary_deg[i]),
                            PositionerSecondaryAngle=float(run.secondary_deg[i]),
                        )
                    ]
                ),
            )
        )
    ds.PerFrameFunctionalGroupsSequence = Sequence(frames)
    return ds
