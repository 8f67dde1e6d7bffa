"""How failures read to a person: a sentence with what to do, never a Python class name."""

from __future__ import annotations

import errno
import re

import pytest

from orbitct_app.error_codes import CATALOGUE, code_for_exception
from orbitct_app.service.core.failures import failure_sentence
from recon.errors import ReconError

CLASS_NAME = re.compile(r"\b[A-Z][a-z]+(?:[A-Z][a-z]+)*(?:Error|Exception|Warning)\b")


@pytest.mark.parametrize(
    ("exc", "said", "code"),
    [
        (ReconError("scan.h5: has no projection frames"), "scan.h5: has no projection frames", "action_failed"),
        (MemoryError(), "ran out of memory: make the work smaller", "action_failed"),
        (
            OSError(errno.ENOSPC, "No space left on device", "/data/x.h5"),
            "(/data/x.h5): No space left on device",
            "insufficient_storage",
        ),
        (OSError(errno.EACCES, "Permission denied", "/data/x.h5"), "(/data/x.h5): Permission denied", "file_error"),
        (KeyError("vectors"), "an unexpected error stopped it ('vectors'); try again", "internal_error"),
        (RuntimeError(), "an unexpected error stopped it (no message)", "internal_error"),
    ],
)
def test_a_failure_is_a_sentence_without_a_class_name(exc: BaseException, said: str, code: str) -> None:
    text = failure_sentence(exc)
    assert said in text and not CLASS_NAME.search(text), text
    assert code_for_exception(exc) == code and code in CATALOGUE
