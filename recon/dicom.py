"""A reconstruction as a DICOM CT image series (one file per axial slice), encoded by pydicom.

The object frame is the DICOM patient frame: patient x, y, z (mm) are the object's x, y, z, so an
axial slice (constant z) has row direction +x and column direction +y. Values are Hounsfield units,
``1000 (mu - mu_water) / mu_water`` from the reconstruction's 1/mm, stored as signed 16-bit integers
(slope 1, intercept 0; clipped to [-1024, 32767]).
"""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from orbitct import __version__
from orbitct.dicom import ENTIRE_BODY, WATER_MU_PER_MM, DicomSeriesOptions, new_instance, sequence_item
from orbitct.geometry import VolumeGrid
from recon.errors import ReconError

HU_RANGE = (-1024, 32767)


@dataclass(frozen=True)
class SeriesInfo:
    """Who and what the series is about; empty patient fields stay empty (DICOM type 2)."""

    description: str = ""
    patient_name: str = ""
    patient_id: str = ""
    study_description: str = ""
    study_uid: str = ""  # empty: a new study
    series_number: int = 1
    water_mu_per_mm: float = WATER_MU_PER_MM
    comments: str = ""  # a caveat every image carries (ImageComments)

    @classmethod
    def from_options(
        cls, options: DicomSeriesOptions, *, description: str, patient_id: str, comments: str = ""
    ) -> SeriesInfo:
        """The series of ``options`` (``patient_id``: the one to use when the options give none)."""
        return cls(
            description=description,
            patient_name=options.patient_name,
            patient_id=options.patient_id or patient_id[:64],
            study_description=options.study_description,
            water_mu_per_mm=options.water_mu_per_mm or WATER_MU_PER_MM,
            comments=comments,
        )


def to_hounsfield(volume: NDArray[np.floating], water_mu_per_mm: float) -> NDArray[np.int16]:
    """Hounsfield units of a 1/mm volume, rounded and clipped to the 16-bit range CT stores."""
    if not water_mu_per_mm > 0:
        raise ReconError(f"water attenuation must be > 0 1/mm, got {water_mu_per_mm!r}")
    hu = 1000.0 * (np.asarray(volume, dtype=np.float64) - water_mu_per_mm) / water_mu_per_mm
    return np.clip(np.rint(np.nan_to_num(hu, nan=HU_RANGE[0])), *HU_RANGE).astype(np.int16)


def _header(ds: Any, info: SeriesInfo, uids: tuple[str, str, str], now: dt.datetime) -> None:
    """Patient, study, series, frame of reference and equipment: the same in every object of a series."""
    date, time = now.strftime("%Y%m%d"), now.strftime("%H%M%S")
    study_uid, series_uid, frame_uid = uids
    ds.Modality, ds.Manufacturer, ds.SoftwareVersions = "CT", "orbitct", __version__
    ds.PatientName, ds.PatientID, ds.PatientBirthDate, ds.PatientSex = info.patient_name, info.patient_id, "", ""
    ds.StudyInstanceUID, ds.StudyDate, ds.StudyTime, ds.StudyID = study_uid, date, time, "1"
    ds.ReferringPhysicianName, ds.AccessionNumber = "", ""
    if info.study_description:
        ds.StudyDescription = info.study_description[:64]
    ds.SeriesInstanceUID, ds.SeriesNumber, ds.SeriesDate, ds.SeriesTime = series_uid, info.series_number, date, time
    ds.SeriesDescription = info.description[:64]
    ds.PatientPosition = ""  # a bench object: not known
    ds.FrameOfReferenceUID, ds.PositionReferenceIndicator = frame_uid, ""
    ds.ContentDate, ds.ContentTime = date, time
    if info.comments:
        ds.ImageComments = info.comments[:10240]


def export_dicom_ct(
    volume: NDArray[np.floating], grid: VolumeGrid, out_dir: Path, info: SeriesInfo = SeriesInfo()
) -> list[Path]:
    """Write ``volume`` (nz, ny, nx; 1/mm) on ``grid`` as a CT series into ``out_dir`` (``CT000001.dcm``, ...)."""
    from pydicom.uid import CTImageStorage, generate_uid

    vol = np.asarray(volume)
    if vol.ndim != 3 or tuple(vol.shape) != tuple(grid.shape):
        raise ReconError(f"volume shape {vol.shape} does not match the grid {grid.shape}")
    hu = to_hounsfield(vol, info.water_mu_per_mm)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    now = dt.datetime.now()
    study_uid = info.study_uid or generate_uid()
    series_uid, frame_uid = generate_uid(), generate_uid()
    vx, vy, vz = grid.voxel_mm
    x0, y0, z0 = grid.origin_mm
    centre = float(np.median(hu)) if hu.size else 0.0
    paths = []
    for k in range(hu.shape[0]):
        ds = new_instance(CTImageStorage)
        _header(ds, info, (study_uid, series_uid, frame_uid), now)
        ds.ImageType = ["DERIVED", "SECONDARY", "AXIAL"]
        ds.Laterality = ""  # a bench object: not known
        ds.InstanceNumber, ds.AcquisitionNumber, ds.KVP = k + 1, 1, ""
        ds.ImagePositionPatient = [f"{x0:.6g}", f"{y0:.6g}", f"{z0 + k * vz:.6g}"]
        ds.ImageOrientationPatient = [1, 0, 0, 0, 1, 0]
        ds.SliceLocation = f"{z0 + k * vz:.6g}"
        ds.PixelSpacing = [f"{vy:.6g}", f"{vx:.6g}"]  # row spacing (between rows: y), column spacing (x)
        ds.SliceThickness = f"{vz:.6g}"
        ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
        ds.Rows, ds.Columns = int(hu.shape[1]), int(hu.shape[2])
        ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 1
        ds.RescaleIntercept, ds.RescaleSlope, ds.RescaleType = 0, 1, "HU"
        ds.WindowCenter, ds.WindowWidth = f"{centre:.0f}", "2000"
        ds.PixelData = np.ascontiguousarray(hu[k]).tobytes()
        path = out_dir / f"CT{k + 1:06d}.dcm"
        ds.save_as(path, enforce_file_format=True)
        paths.append(path)
    return paths


def export_enhanced_ct(
    volume: NDArray[np.floating], grid: VolumeGrid, out: Path, info: SeriesInfo = SeriesInfo()
) -> Path:
    """Write ``volume`` (nz, ny, nx; 1/mm) on ``grid`` as one Enhanced CT object ``out``: one frame per axial slice,
    spacing, orientation and rescale shared, each frame's position in its own functional group."""
    from pydicom.sequence import Sequence
    from pydicom.uid import EnhancedCTImageStorage, generate_uid

    vol = np.asarray(volume)
    if vol.ndim != 3 or tuple(vol.shape) != tuple(grid.shape):
        raise ReconError(f"volume shape {vol.shape} does not match the grid {grid.shape}")
    hu = to_hounsfield(vol, info.water_mu_per_mm)
    now = dt.datetime.now()
    ds = new_instance(EnhancedCTImageStorage)
    _header(ds, info, (info.study_uid or generate_uid(), generate_uid(), generate_uid()), now)
    vx, vy, vz = grid.voxel_mm
    x0, y0, z0 = grid.origin_mm
    ds.ManufacturerModelName, ds.DeviceSerialNumber = "orbitct", "0"
    ds.ImageType = ["DERIVED", "PRIMARY", "VOLUME", "NONE"]  # Enhanced CT allows PRIMARY only
    ds.InstanceNumber, ds.AcquisitionNumber = 1, 1
    ds.AcquisitionDateTime = now.strftime("%Y%m%d%H%M%S")
    ds.AcquisitionDuration = 0.0
    ds.ContentQualification, ds.BurnedInAnnotation, ds.LossyImageCompression = "RESEARCH", "NO", "00"
    ds.RecognizableVisualFeatures = "NO"
    ds.PresentationLUTShape = "IDENTITY"
    ds.PixelPresentation, ds.VolumetricProperties, ds.VolumeBasedCalculationTechnique = "MONOCHROME", "VOLUME", "NONE"
    ds.AcquisitionContextSequence = Sequence()
    ds.NumberOfFrames = int(hu.shape[0])
    ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
    ds.Rows, ds.Columns = int(hu.shape[1]), int(hu.shape[2])
    ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 1
    dim_uid = generate_uid()
    ds.DimensionOrganizationSequence = Sequence([sequence_item(DimensionOrganizationUID=dim_uid)])
    ds.DimensionOrganizationType = "3D"
    ds.DimensionIndexSequence = Sequence(
        [
            sequence_item(
                DimensionOrganizationUID=dim_uid,
                DimensionIndexPointer=0x00200032,
                FunctionalGroupPointer=0x00209113,
                DimensionDescriptionLabel="Image position",
            )
        ]
    )
    centre = float(np.median(hu)) if hu.size else 0.0
    ds.SharedFunctionalGroupsSequence = Sequence(
        [
            sequence_item(
                PixelMeasuresSequence=Sequence(
                    [
                        sequence_item(
                            PixelSpacing=[f"{vy:.6g}", f"{vx:.6g}"],
                            SliceThickness=f"{vz:.6g}",
                            SpacingBetweenSlices=f"{vz:.6g}",
                        )
                    ]
                ),
                PlaneOrientationSequence=Sequence([sequence_item(ImageOrientationPatient=[1, 0, 0, 0, 1, 0])]),
                PixelValueTransformationSequence=Sequence(
                    [sequence_item(RescaleIntercept=0, RescaleSlope=1, RescaleType="HU")]
                ),
                FrameVOILUTSequence=Sequence([sequence_item(WindowCenter=f"{centre:.0f}", WindowWidth="2000")]),
                FrameAnatomySequence=Sequence(
                    [
                        sequence_item(
                            FrameLaterality="U", AnatomicRegionSequence=Sequence([sequence_item(**ENTIRE_BODY)])
                        )
                    ]
                ),
                IrradiationEventIdentificationSequence=Sequence([sequence_item(IrradiationEventUID=generate_uid())]),
                CTImageFrameTypeSequence=Sequence(
                    [
                        sequence_item(
                            FrameType=["DERIVED", "PRIMARY", "VOLUME", "NONE"],
                            PixelPresentation="MONOCHROME",
                            VolumetricProperties="VOLUME",
                            VolumeBasedCalculationTechnique="NONE",
                        )
                    ]
                ),
            )
        ]
    )
    frames = []
    for k in range(hu.shape[0]):
        frames.append(
            sequence_item(
                FrameContentSequence=Sequence([sequence_item(DimensionIndexValues=[k + 1], FrameAcquisitionNumber=1)]),
                PlanePositionSequence=Sequence(
                    [sequence_item(ImagePositionPatient=[f"{x0:.6g}", f"{y0:.6g}", f"{z0 + k * vz:.6g}"])]
                ),
            )
        )
    ds.PerFrameFunctionalGroupsSequence = Sequence(frames)
    ds.PixelData = np.ascontiguousarray(hu).tobytes()
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    ds.save_as(out, enforce_file_format=True)
    return out
