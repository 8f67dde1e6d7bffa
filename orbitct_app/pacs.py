"""A PACS node over DICOM networking (pynetdicom): send a series (C-STORE), find series (C-FIND), fetch one (C-GET).

A node is a URI ``dicom://AE_TITLE@host:port``; orbitct calls itself ``ORBITCT`` unless told otherwise.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

CALLING_AET = "ORBITCT"
TIMEOUT_S = 30.0


class PacsError(Exception):
    """The node could not be reached, refused the association, or answered a request with a failure."""


@dataclass(frozen=True)
class PacsNode:
    """Where a DICOM node listens and its AE title."""

    ae_title: str
    host: str
    port: int

    @classmethod
    def parse(cls, uri: str) -> PacsNode:
        """``dicom://AE@host:port``; a one-line error naming what is wrong otherwise."""
        parts = urlsplit(uri)
        if parts.scheme != "dicom" or not parts.username or not parts.hostname or parts.port is None:
            raise PacsError(
                f"PACS node {uri!r}: expected dicom://AE_TITLE@host:port (e.g. dicom://ORTHANC@127.0.0.1:4242)"
            )
        if not 1 <= len(parts.username) <= 16:
            raise PacsError(f"PACS node {uri!r}: an AE title has 1 to 16 characters")
        return cls(parts.username, parts.hostname, int(parts.port))

    def __str__(self) -> str:
        return f"dicom://{self.ae_title}@{self.host}:{self.port}"


def _associate(node: PacsNode, contexts: Sequence[Any], calling: str, **kwargs: Any) -> Any:
    from pynetdicom import AE

    ae = AE(ae_title=calling)
    ae.acse_timeout = ae.dimse_timeout = ae.network_timeout = TIMEOUT_S
    for context in contexts:
        ae.add_requested_context(context)
    assoc = ae.associate(node.host, node.port, ae_title=node.ae_title, **kwargs)
    if not assoc.is_established:
        raise PacsError(f"{node}: no association (the node is down, or refused AE title {calling!r})")
    return assoc


def send(files: Sequence[Path], node: PacsNode, calling: str = CALLING_AET) -> int:
    """C-STORE every file to ``node``; the number stored (PacsError on the first failure; a store that gets no
    answer is tried once more on a new association)."""
    import pydicom

    datasets = [pydicom.dcmread(f) for f in files]
    classes = sorted({str(ds.SOPClassUID) for ds in datasets})
    assoc = _associate(node, classes, calling)
    try:
        for f, ds in zip(files, datasets):
            status = assoc.send_c_store(ds)
            if not status and not assoc.is_established:
                # no answer within the DIMSE timeout, and pynetdicom aborted the association. Under load its
                # reactor thread can take a response meant for the request just sent ("Received unexpected
                # C-STORE service message"): store the object once more on a new association (storing an
                # instance again is harmless); a node that is down or stays silent fails below
                assoc = _associate(node, classes, calling)
                status = assoc.send_c_store(ds)
            if not status or int(status.Status) not in (0x0000, 0xB000, 0xB007, 0xB006):
                code = f"0x{int(status.Status):04X}" if status else "no answer"
                raise PacsError(f"{node}: storing {Path(f).name} failed ({code})")
    finally:
        assoc.release()
    return len(datasets)


RETRIEVED_CLASSES = (
    "1.2.840.10008.5.1.4.1.1.2",
    "1.2.840.10008.5.1.4.1.1.2.1",  # CT, Enhanced CT
    "1.2.840.10008.5.1.4.1.1.12.1",
    "1.2.840.10008.5.1.4.1.1.12.1.1",  # XA, Enhanced XA
    "1.2.840.10008.5.1.4.1.1.12.2",
    "1.2.840.10008.5.1.4.1.1.12.2.1",
)  # XRF, Enhanced XRF
SERIES_KEYS = (
    "StudyInstanceUID",
    "SeriesInstanceUID",
    "Modality",
    "SeriesDescription",
    "PatientID",
    "NumberOfSeriesRelatedInstances",
)


def find_series(node: PacsNode, calling: str = CALLING_AET, **match: str) -> list[dict[str, str]]:
    """C-FIND at series level (study root); ``match`` narrows it (``PatientID=``, ``Modality=``, ...)."""
    from pydicom.dataset import Dataset
    from pynetdicom.sop_class import StudyRootQueryRetrieveInformationModelFind  # type: ignore[attr-defined]  # made at import

    query = Dataset()
    query.QueryRetrieveLevel = "SERIES"
    for key in SERIES_KEYS:
        setattr(query, key, match.get(key, ""))
    assoc = _associate(node, [StudyRootQueryRetrieveInformationModelFind], calling)
    found = []
    try:
        for status, identifier in assoc.send_c_find(query, StudyRootQueryRetrieveInformationModelFind):
            if not status:
                raise PacsError(f"{node}: the query got no answer")
            if int(status.Status) in (0xFF00, 0xFF01) and identifier is not None:
                found.append({k: str(identifier.get(k, "")) for k in SERIES_KEYS})
            elif int(status.Status) != 0x0000:
                raise PacsError(f"{node}: the query failed (0x{int(status.Status):04X})")
    finally:
        assoc.release()
    return found


def get_series(
    node: PacsNode,
    study_uid: str,
    series_uid: str,
    out_dir: Path,
    calling: str = CALLING_AET,
    sop_classes: Sequence[str] = (),
) -> list[Path]:
    """C-GET one series into ``out_dir`` (the node sends it back on the same association); the files written."""
    from pydicom.dataset import Dataset
    from pynetdicom import build_role, evt
    from pynetdicom.sop_class import StudyRootQueryRetrieveInformationModelGet  # type: ignore[attr-defined]  # made at import

    classes = list(sop_classes) or list(RETRIEVED_CLASSES)
    out_dir.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []

    def on_store(event: Any) -> int:
        ds = event.dataset
        ds.file_meta = event.file_meta
        path = out_dir / f"{ds.SOPInstanceUID}.dcm"
        ds.save_as(path, enforce_file_format=True)
        written.append(path)
        return 0x0000

    query = Dataset()
    query.QueryRetrieveLevel = "SERIES"
    query.StudyInstanceUID, query.SeriesInstanceUID = study_uid, series_uid
    assoc = _associate(
        node,
        [StudyRootQueryRetrieveInformationModelGet, *classes],
        calling,
        ext_neg=[build_role(c, scp_role=True) for c in classes],
        evt_handlers=[(evt.EVT_C_STORE, on_store)],
    )
    try:
        for status, _ in assoc.send_c_get(query, StudyRootQueryRetrieveInformationModelGet):
            if status and int(status.Status) not in (0x0000, 0xFF00, 0xB000):
                raise PacsError(f"{node}: retrieving series {series_uid} failed (0x{int(status.Status):04X})")
    finally:
        assoc.release()
    if not written:
        raise PacsError(f"{node}: series {series_uid} came back empty (unknown to the node?)")
    return written
