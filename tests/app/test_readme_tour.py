"""The README's tour, command by command, exactly as written there (in a fresh folder, with the installed
``orbitct``): what a new user types after ``make demo`` must work."""

from __future__ import annotations

import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

from tests.helpers.service import free_port

pytestmark = [pytest.mark.system, pytest.mark.slow, pytest.mark.timeout(900)]
ROOT = Path(__file__).resolve().parents[2]


def tour_commands() -> list[str]:
    """The commands of the README's ``## The pipeline in one tour`` code block (continuations joined, comments cut)."""
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    section = text.split("## The pipeline in one tour", 1)[1]
    block = re.search(r"```sh\n(.*?)```", section, re.S)
    assert block, "the tour has no sh block"
    commands, current = [], ""
    for line in block.group(1).splitlines():
        code = line.split("#", 1)[0].rstrip()
        if not code.strip():
            continue
        if code.endswith("\\"):
            current += code[:-1] + " "
            continue
        commands.append((current + code).strip())
        current = ""
    return commands


def test_the_readme_tour_runs_as_written(tmp_path: Path) -> None:
    commands = tour_commands()
    assert commands and all(c.startswith("orbitct ") for c in commands), commands
    shutil.copytree(ROOT / "config", tmp_path / "config")
    exe = Path(sys.executable).parent / "orbitct"
    env = {**os.environ, "PATH": f"{exe.parent}{os.pathsep}{os.environ.get('PATH', '')}"}
    for command in commands:
        argv = shlex.split(command)
        if argv[1] == "serve":  # runs until stopped: it must come up healthy, then stop cleanly
            port = free_port()
            proc = subprocess.Popen(
                [*argv, "--port", str(port), "--data-dir", str(tmp_path / "data")],
                cwd=tmp_path,
                env=env,
                stdout=subprocess.PIPE,
                stderr=subprocess.STDOUT,
                text=True,
            )
            try:
                t0 = time.monotonic()
                while True:
                    assert proc.poll() is None, proc.communicate()[0]
                    try:
                        if httpx.get(f"http://127.0.0.1:{port}/health", timeout=2).json()["bench"] == "connected":
                            break
                    except httpx.HTTPError:
                        pass
                    assert time.monotonic() - t0 < 120, "orbitct serve did not come up"
                    time.sleep(0.5)
            finally:
                proc.send_signal(signal.SIGINT)
                out, _ = proc.communicate(timeout=60)
            assert proc.returncode == 0, out
            continue
        done = subprocess.run(argv, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
        assert done.returncode == 0, (command, done.stdout[-2000:], done.stderr[-2000:])
        assert "Traceback" not in done.stderr, (command, done.stderr[-2000:])
    assert (tmp_path / "scanA.h5").is_file() and (tmp_path / "scan.h5").is_file()
    assert any((tmp_path / "calib-report").iterdir())
