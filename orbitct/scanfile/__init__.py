"""Scan files (HDF5, ``docs/scan-file.md`` version 1): image keys, streaming writer, validating reader, frames
read from any thread, results (calibration, reconstructions, status), the one scan summary, and files that read
their frames from another scan file."""

from orbitct.scanfile.errors import DiskFullError, ScanFileError
from orbitct.scanfile.frames import FrameReader
from orbitct.scanfile.keys import ImageKey
from orbitct.scanfile.linked import write_linked_scan
from orbitct.scanfile.reader import ScanFile, describe_frame_problems, frame_problem
from orbitct.scanfile.summary import scan_summary
from orbitct.scanfile.writer import FORMAT, VERSION, ScanWriter

__all__ = [
    "FORMAT",
    "VERSION",
    "DiskFullError",
    "FrameReader",
    "ImageKey",
    "ScanFile",
    "ScanFileError",
    "ScanWriter",
    "describe_frame_problems",
    "frame_problem",
    "scan_summary",
    "write_linked_scan",
]
