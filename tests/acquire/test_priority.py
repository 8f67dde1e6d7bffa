"""The acquisition's priority: raised for every thread where permitted, restored afterwards, refused quietly."""

from __future__ import annotations

import os
import subprocess
import sys
import threading

from acquire.priority import BENCH_NICE, bench_priority


def _nice(tid: int) -> int:
    return os.getpriority(os.PRIO_PROCESS, tid)


def test_every_thread_runs_at_the_bench_priority_and_returns_to_its_own() -> None:
    started = threading.Event()
    release = threading.Event()
    tids: dict[str, int] = {}

    def worker(name: str) -> None:
        tids[name] = threading.get_native_id()
        started.set()
        release.wait(10)

    before = threading.Thread(target=worker, args=("before",), daemon=True)
    before.start()
    started.wait(10)
    own = _nice(0)
    permitted = os.geteuid() == 0  # root (CI) may raise priority; a user without CAP_SYS_NICE may not
    with bench_priority() as raised:
        assert raised is permitted
        started.clear()
        inside = threading.Thread(target=worker, args=("inside",), daemon=True)
        inside.start()
        started.wait(10)
        expected = BENCH_NICE if permitted else own
        assert _nice(0) == _nice(tids["before"]) == _nice(tids["inside"]) == expected
    assert _nice(0) == _nice(tids["before"]) == _nice(tids["inside"]) == own
    release.set()


def test_without_the_permission_the_scan_runs_at_normal_priority() -> None:
    """As a user without CAP_SYS_NICE (root drops to nobody first): nothing raised, nothing changed, no error."""
    drop = "os.setuid(65534)" if os.geteuid() == 0 else "pass"  # after the import: nobody cannot read the venv
    code = "\n".join(
        [
            "import os",
            "from acquire.priority import bench_priority",
            drop,
            "own = os.getpriority(os.PRIO_PROCESS, 0)",
            "with bench_priority() as raised:",
            "    assert raised is False and os.getpriority(os.PRIO_PROCESS, 0) == own",
            "print('normal')",
        ]
    )
    out = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=os.getcwd(),
        env={**os.environ, "PYTHONPATH": os.getcwd()},
    )
    assert out.returncode == 0 and out.stdout.strip() == "normal", out.stderr
