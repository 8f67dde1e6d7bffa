"""Errors raised by scan-file reading and writing."""


class ScanFileError(ValueError):
    """A scan file that is missing, malformed, or used the wrong way; the message names file and problem."""
