"""The commands the README's tour and the tutorials show, exactly as written there (in a fresh folder, with the
installed ``orbitct``): what a new user types after ``make demo`` must work."""

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


def sh_commands(text: str) -> list[str]:
    """The commands of every ``sh`` block in ``text`` (continuations joined, comments cut). Blocks marked ``bash``
    or ``text`` are shown, not run: they need hardware, a token or a running service."""
    commands, current = [], ""
    for block in re.findall(r"```sh\n(.*?)```", text, re.S):
        for line in block.splitlines():
            code = line.split("#", 1)[0].rstrip()
            if not code.strip():
                continue
            if code.endswith("\\"):
                current += code[:-1] + " "
                continue
            commands.append((current + code).strip())
            current = ""
    return commands


def tour_commands() -> list[str]:
    """The commands of the README's ``## The pipeline in one tour`` section."""
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    section = text.split("## The pipeline in one tour", 1)[1].split("\n## ", 1)[0]
    commands = sh_commands(section)
    assert commands, "the tour has no sh block"
    return commands


def run_as_written(commands: list[str], folder: Path) -> None:
    """Run each command in ``folder`` as a user would; ``orbitct serve`` must come up healthy and stop cleanly."""
    assert commands and all(c.startswith("orbitct ") for c in commands), commands
    shutil.copytree(ROOT / "config", folder / "config", dirs_exist_ok=True)
    exe = Path(sys.executable).parent / "orbitct"
    env = {**os.environ, "PATH": f"{exe.parent}{os.pathsep}{os.environ.get('PATH', '')}"}
    for command in commands:
        argv = shlex.split(command)
        if argv[1] == "serve":  # runs until stopped: it must come up healthy, then stop cleanly
            port = free_port()
            proc = subprocess.Popen(
                [*argv, "--port", str(port), "--data-dir", str(folder / "data")],
                cwd=folder,
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
        done = subprocess.run(argv, cwd=folder, env=env, capture_output=True, text=True, timeout=600)
        assert done.returncode == 0, (command, done.stdout[-2000:], done.stderr[-2000:])
        assert "Traceback" not in done.stderr, (command, done.stderr[-2000:])


def test_the_readme_tour_runs_as_written(tmp_path: Path) -> None:
    run_as_written(tour_commands(), tmp_path)
    assert (tmp_path / "scanA.h5").is_file() and (tmp_path / "scan.h5").is_file()
    assert any((tmp_path / "calib-report").iterdir())


# The tutorials with commands to run (the lab technician's works in a browser: tests/app/console/test_browser.py).
RUNNABLE = [p for p in sorted((ROOT / "docs" / "tutorials").glob("*.md")) if sh_commands(p.read_text("utf-8"))]


def test_the_operator_and_ci_tutorials_have_commands_to_run() -> None:
    assert {p.stem for p in RUNNABLE} >= {"bench-operator", "ci-user"}


@pytest.mark.parametrize("page", RUNNABLE, ids=lambda p: p.stem)
def test_a_tutorial_runs_as_written(page: Path, tmp_path: Path) -> None:
    run_as_written(sh_commands(page.read_text(encoding="utf-8")), tmp_path)
