"""Scan files (HDF5, ``scan-file.md`` version 1): streaming writer and validating reader."""

from orbitct.scanfile.errors import ScanFileError
from orbitct.scanfile.reader import ScanFile
from orbitct.scanfile.writer import FORMAT, IMAGE_KEYS, VERSION, ScanWriter

__all__ = ["FORMAT", "IMAGE_KEYS", "VERSION", "ScanFile", "ScanFileError", "ScanWriter"]
