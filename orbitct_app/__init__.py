"""The roof of orbitct: the ``orbitct`` command line, the REST service and the web console.

Nothing imports this package; it imports the ground (``orbitct``) and the walls
(``devices``, ``acquire``, ``calib``, ``recon``).
"""
