"""A real Orthanc PACS on loopback (Debian's ``orthanc``), with a temporary configuration and storage."""

from __future__ import annotations

import json
import socket
import subprocess
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from orbitct_app.pacs import PacsNode
from tests.helpers.service import free_port
from tests.helpers.tools import require_tool


@contextmanager
def orthanc(folder: Path) -> Iterator[PacsNode]:
    """Orthanc listening on a free DICOM port; fails in CI (``.ci/run`` installs it) and skips elsewhere if missing."""
    exe = require_tool("Orthanc", "orthanc")
    port = free_port()
    config = {
        "Name": "orbitct-tests",
        "StorageDirectory": str(folder / "storage"),
        "IndexDirectory": str(folder / "index"),
        "DicomAet": "ORTHANC",
        "DicomPort": port,
        "HttpPort": free_port(),
        "RemoteAccessAllowed": False,
        "AuthenticationEnabled": False,
        "DicomCheckCalledAet": False,
        "DicomAlwaysAllowStore": True,
        "DicomAlwaysAllowFind": True,
        "DicomAlwaysAllowGet": True,
        "DicomAlwaysAllowMove": True,
        "DicomModalities": {"orbitct": ["ORBITCT", "127.0.0.1", 11112]},
        "Plugins": [],
    }
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "orthanc.json"
    path.write_text(json.dumps(config))
    proc = subprocess.Popen([exe, str(path)], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        t0 = time.monotonic()
        while True:
            try:
                with socket.create_connection(("127.0.0.1", port), timeout=0.5):
                    break
            except OSError:
                if proc.poll() is not None or time.monotonic() - t0 > 30:
                    raise AssertionError(
                        "Orthanc did not start: " + (proc.stderr.read() or b"").decode()[-2000:]
                    ) from None  # type: ignore[union-attr]
                time.sleep(0.2)
        yield PacsNode("ORTHANC", "127.0.0.1", port)
    finally:
        proc.terminate()
        try:
            proc.wait(15)
        except subprocess.TimeoutExpired:
            proc.kill()
