"""Background work: calibration and reconstruction jobs (the queue and Dask worker processes, and what a worker
runs), and BB plans (one at a time, each in a process of its own)."""
