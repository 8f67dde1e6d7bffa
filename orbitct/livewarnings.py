"""What a live calibration can warn about while a scan runs, in one place.

The calibration raises these warnings (:mod:`calib.follow`), the CLI, the REST request and the console offer the
ones a scan may be stopped on. This module is light (no NumPy) so that ``orbitct scan`` starts quickly.
"""

from __future__ import annotations

from typing import Literal, get_args

#: what a live warning can be about
WarningKind = Literal["bb_lost", "bb_found", "bb_left_fov", "few_bbs", "bb_distorted", "object_moved", "fell_behind"]
#: the warnings a scan may be stopped on: all but the good news ("bb_found")
AbortKind = Literal["bb_lost", "bb_left_fov", "few_bbs", "bb_distorted", "object_moved", "fell_behind"]

#: each kind, and in a few words what it says (the console's choices)
WARNING_MEANINGS: dict[str, str] = {
    "bb_lost": "a BB is lost",
    "bb_found": "a lost BB is found again",
    "bb_left_fov": "a BB leaves the panel",
    "few_bbs": "a view shows too few BBs",
    "bb_distorted": "a BB looks distorted (over metal or bone, or merged)",
    "object_moved": "the object moved on the table",
    "fell_behind": "calibration falls behind",
}
WARNING_KINDS: tuple[str, ...] = get_args(WarningKind)
ABORT_KINDS: tuple[str, ...] = get_args(AbortKind)

if set(WARNING_MEANINGS) != set(WARNING_KINDS) or set(ABORT_KINDS) != set(WARNING_KINDS) - {"bb_found"}:
    raise ImportError("orbitct.livewarnings: the kinds, their meanings and the abort kinds disagree")
