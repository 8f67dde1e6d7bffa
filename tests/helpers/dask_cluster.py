"""A real Dask cluster on loopback for the tests: ``dask scheduler`` and ``dask worker`` processes, as a lab runs them."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[2]
DASK = str(Path(sys.executable).with_name("dask"))


class DaskCluster:
    """A scheduler and ``n`` workers (one thread each, with their nannies) started in ``folder``; they import
    orbitct from this checkout."""

    def __init__(self, folder: Path, n_workers: int = 2) -> None:
        self.folder = folder
        self.file = folder / "scheduler.json"
        self.env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
        self.scheduler = self._start(
            [
                DASK,
                "scheduler",
                "--host",
                "127.0.0.1",
                "--port",
                "0",
                "--no-dashboard",
                "--scheduler-file",
                str(self.file),
            ],
            "scheduler",
        )
        deadline = time.monotonic() + 60.0
        while not self.file.exists():
            if time.monotonic() > deadline or self.scheduler.poll() is not None:
                raise RuntimeError(f"dask scheduler did not start: {self._log('scheduler')}")
            time.sleep(0.1)
        self.address = str(json.loads(self.file.read_text())["address"])
        self.workers = [
            self._start(
                [
                    DASK,
                    "worker",
                    "--scheduler-file",
                    str(self.file),
                    "--nthreads",
                    "1",
                    "--no-dashboard",
                    "--host",
                    "127.0.0.1",
                    "--memory-limit",
                    "0",
                    "--name",
                    f"w{i}",
                ],
                f"worker{i}",
            )
            for i in range(n_workers)
        ]

    def _start(self, cmd: list[str], name: str) -> subprocess.Popen[bytes]:
        log = open(self.folder / f"{name}.log", "wb")  # noqa: SIM115 - closed with the process
        return subprocess.Popen(
            cmd, stdout=log, stderr=subprocess.STDOUT, env=self.env, cwd=ROOT, start_new_session=True
        )

    def _log(self, name: str) -> str:
        path = self.folder / f"{name}.log"
        return path.read_text(errors="replace")[-2000:] if path.exists() else ""

    def client(self, workers: int | None = None, timeout_s: float = 60.0) -> Any:
        """A client of this cluster, once ``workers`` (default all) have joined."""
        from distributed import Client

        c = Client(self.address, timeout=timeout_s, set_as_default=False)
        c.wait_for_workers(len(self.workers) if workers is None else workers, timeout=timeout_s)
        return c

    def kill_scheduler(self) -> None:
        """The scheduler's machine goes away."""
        os.killpg(self.scheduler.pid, signal.SIGKILL)
        self.scheduler.wait(10)

    def close(self) -> None:
        """Stop every process of the cluster."""
        for proc in [*self.workers, self.scheduler]:
            if proc.poll() is None:
                try:
                    os.killpg(proc.pid, signal.SIGTERM)
                except ProcessLookupError:
                    continue
        for proc in [*self.workers, self.scheduler]:
            try:
                proc.wait(15)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait(5)
