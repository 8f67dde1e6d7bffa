"""How a failure reads to a person: one sentence of what happened and what to do, never a class name."""

from __future__ import annotations


def failure_sentence(exc: BaseException) -> str:
    """What a failure says to a person (a job's reason, a plan's, a bench command's): orbitct's own errors in their
    words (they name what was wrong and what to do), the machine's in plain terms, anything else as unexpected;
    never a class name or a traceback."""
    text = str(exc).strip()
    if isinstance(exc, MemoryError):
        return (
            "it ran out of memory: make the work smaller (a smaller volume or fewer views) or use a machine with more"
        )
    if isinstance(exc, OSError) and not isinstance(exc, TimeoutError | ConnectionError):
        where = f" ({exc.filename})" if exc.filename else ""
        return f"a file could not be read or written{where}: {exc.strerror or text}; check the disk and try again"
    if isinstance(exc, ValueError) and text:  # orbitct's errors (ScanFileError, ReconError, CalibrationError...)
        return text
    return (
        f"an unexpected error stopped it ({text or 'no message'}); try again, and if it fails again report it (the "
        "service's log has the details)"
    )
