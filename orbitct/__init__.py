"""orbitct: non-circular cone-beam CT orbits on real hardware.

This package is the ground every other package stands on: geometry, rotations,
kinematics, error profiles, progress events, scan files, orbits, phantoms and
the projection simulator. It imports none of the other packages.
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("orbitct")
except PackageNotFoundError:  # running from a source tree without install
    __version__ = "0.0.0+source"
