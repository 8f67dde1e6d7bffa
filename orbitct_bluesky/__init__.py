"""orbitct in a bluesky stack: a callback that writes orbitct's scan file from a run's documents.

An adapter the rest of orbitct never imports; install it with ``pip install 'orbitct[bluesky]'`` (it needs
``event-model``). The documents a run must carry are described in :mod:`orbitct_bluesky.scanfile_callback` and in
the documentation (how-to: *Record scans with bluesky*).
"""

from __future__ import annotations

from orbitct_bluesky.scanfile_callback import ScanFileCallback, orbitct_metadata

__all__ = ["ScanFileCallback", "orbitct_metadata"]
