"""orbitct in a bluesky stack: ophyd-async devices over orbitct's drivers, a plan for an orbit, a callback
that writes orbitct's scan file from a run's documents, and one that calibrates it live.

An adapter the rest of orbitct never imports; install it with ``pip install 'orbitct[bluesky]'`` (bluesky,
ophyd-async and event-model). The documents a run must carry are described in
:mod:`orbitct_bluesky.scanfile_callback` and in the documentation (how-to: *Use orbitct devices from bluesky*).
"""

from __future__ import annotations

from orbitct_bluesky.devices import FlatPanel, Hexapod, RotationStage, XrayGenerator
from orbitct_bluesky.live_callback import LiveCalibrationCallback
from orbitct_bluesky.plan import Bench, orbit_plan
from orbitct_bluesky.scanfile_callback import ScanFileCallback, orbitct_metadata

__all__ = [
    "Bench",
    "FlatPanel",
    "Hexapod",
    "LiveCalibrationCallback",
    "RotationStage",
    "ScanFileCallback",
    "XrayGenerator",
    "orbit_plan",
    "orbitct_metadata",
]
