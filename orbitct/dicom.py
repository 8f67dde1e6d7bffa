"""The start of every DICOM object orbitct writes (pydicom encodes it): file meta, SOP identity, character set."""

from __future__ import annotations

from typing import Any


def new_instance(sop_class_uid: str) -> Any:
    """A pydicom ``Dataset`` of ``sop_class_uid`` with a fresh SOP instance UID, its file meta (explicit VR little
    endian) and the Latin-1 character set; the caller adds its modules."""
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.uid import (
        PYDICOM_IMPLEMENTATION_UID,
        ExplicitVRLittleEndian,
        generate_uid,
    )

    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = sop_class_uid
    meta.MediaStorageSOPInstanceUID = generate_uid()
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    meta.ImplementationClassUID = PYDICOM_IMPLEMENTATION_UID
    ds = Dataset()
    ds.file_meta = meta
    ds.SpecificCharacterSet = "ISO_IR 100"
    ds.SOPClassUID, ds.SOPInstanceUID = sop_class_uid, meta.MediaStorageSOPInstanceUID
    return ds
