"""Errors raised by scan-file reading and writing."""


class ScanFileError(ValueError):
    """A scan file that is missing, malformed, or used the wrong way; the message names file and problem."""


class DiskFullError(ScanFileError):
    """A frame was not written because the disk is (nearly) full; the frames before it are kept."""
