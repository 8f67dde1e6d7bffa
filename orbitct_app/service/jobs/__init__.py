"""Calibration and reconstruction jobs: the queue and worker processes, and what a worker runs."""
