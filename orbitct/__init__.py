"""orbitct: non-circular cone-beam CT orbits on real hardware.

This package holds the shared core (geometry, rotations, scan files, orbits,
error profiles, phantoms and the projection simulator) and, on top of all
packages, the command line (``orbitct.cli``) and the REST service
(``orbitct.service``).
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("orbitct")
except PackageNotFoundError:  # running from a source tree without install
    __version__ = "0.0.0+source"
