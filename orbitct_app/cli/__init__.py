"""The ``orbitct`` command line (sits on top of every package)."""
