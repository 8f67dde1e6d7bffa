"""``orbitct twin ...`` as a separate process, as a lab starts it."""

from __future__ import annotations

import re
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager


@contextmanager
def twin_process(*args: str) -> Iterator[tuple[int, subprocess.Popen[str]]]:
    """Start ``orbitct twin ARGS --port 0 --console``; yield the port it printed and the process."""
    cmd = [
        sys.executable,
        "-c",
        "from orbitct_app.cli.main import main; main()",
        "twin",
        *args,
        "--port",
        "0",
        "--console",
    ]
    proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stderr is not None
        line = proc.stderr.readline()
        match = re.search(r"127\.0\.0\.1:(\d+)", line)
        assert match, f"no port in {line!r}"
        yield int(match.group(1)), proc
    finally:
        proc.terminate()
        proc.wait(10)
