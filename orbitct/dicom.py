"""The start of every DICOM object orbitct writes (pydicom encodes it): file meta, SOP identity, character set; and
the items its sequences (functional groups, codes) are made of."""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, Field

WATER_MU_PER_MM = 0.0206  # the simulator's water at its effective energy (orbitct.phantoms.materials)


def new_instance(sop_class_uid: str) -> Any:
    """A pydicom ``Dataset`` of ``sop_class_uid`` with a fresh SOP instance UID, its file meta (explicit VR little
    endian) and the Latin-1 character set; the caller adds its modules."""
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.uid import (
        PYDICOM_IMPLEMENTATION_UID,
        UID,
        ExplicitVRLittleEndian,
        generate_uid,
    )

    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = UID(sop_class_uid)
    meta.MediaStorageSOPInstanceUID = generate_uid()
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    meta.ImplementationClassUID = PYDICOM_IMPLEMENTATION_UID
    ds = Dataset()
    ds.file_meta = meta
    ds.SpecificCharacterSet = "ISO_IR 100"
    ds.SOPClassUID, ds.SOPInstanceUID = sop_class_uid, meta.MediaStorageSOPInstanceUID
    return ds


def sequence_item(**attrs: Any) -> Any:
    """A pydicom ``Dataset`` to put in a sequence, with the attributes given by keyword."""
    from pydicom.dataset import Dataset

    item = Dataset()
    for key, value in attrs.items():
        setattr(item, key, value)
    return item


#: the anatomic region of a whole object (SNOMED CT "Entire body"): what a bench object or phantom is
ENTIRE_BODY = {"CodeValue": "38266002", "CodingSchemeDesignator": "SCT", "CodeMeaning": "Entire body"}


class DicomSeriesOptions(BaseModel):
    """How a reconstruction is written as DICOM: the Hounsfield scale, the patient and study fields, and one
    Enhanced CT object or one CT image per slice (``recon.dicom`` writes it). ``orbitct export dicom`` makes its options from it, and the REST
    service's ``GET /reconstructions/{id}/dicom`` and ``POST /pacs/{node}/store`` take it."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    water_mu_per_mm: float | None = Field(
        None,
        gt=0.0,
        le=10.0,
        description=f"attenuation of water (1/mm) for Hounsfield units (default {WATER_MU_PER_MM}, the simulator's)",
    )
    patient_name: str = Field("", max_length=64, pattern=r"^[^\\\x00-\x1f]*$", description="DICOM Patient's Name")
    patient_id: str = Field(
        "", max_length=64, pattern=r"^[\w .-]*$", description="DICOM Patient ID (default: the scan's name)"
    )
    study_description: str = Field(
        "", max_length=64, pattern=r"^[^\\\x00-\x1f]*$", description="DICOM Study Description"
    )
    enhanced: bool = Field(False, description="one multi-frame Enhanced CT object instead of one CT image per slice")
