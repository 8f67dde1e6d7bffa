"""The start of every DICOM object orbitct writes (pydicom encodes it): file meta, SOP identity, character set; and
the items its sequences (functional groups, codes) are made of."""

from __future__ import annotations

from typing import Any


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
