"""Fixtures every test module shares."""

from __future__ import annotations

import gc
import os
import sys
from collections.abc import Iterator

import pytest


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(
        "--gpu", action="store_true", help="run the tests marked gpu on this machine's GPU (make test-gpu), only them"
    )


def pytest_configure(config: pytest.Config) -> None:
    """Without ``--gpu`` numba's CUDA simulator stands in for a GPU (before anything imports numba.cuda): the CUDA
    kernels' tests run on the CPU, and ``device=auto`` still picks the CPU (recon.device)."""
    if not config.getoption("--gpu"):
        os.environ["NUMBA_ENABLE_CUDASIM"] = "1"
        if "numba" in sys.modules:  # a plugin imported it already: read the environment again
            from numba.core import config as numba_config

            numba_config.reload_config()


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """``--gpu`` runs the tests marked gpu and only them; without it they are left out."""
    on_gpu = bool(config.getoption("--gpu"))
    keep = [item for item in items if (item.get_closest_marker("gpu") is not None) == on_gpu]
    if len(keep) != len(items):
        config.hook.pytest_deselected(items=[item for item in items if item not in keep])
        items[:] = keep


@pytest.fixture(scope="session", autouse=True)
def _cache_of_the_session(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    """Caches (PWLS's data curvature) go to a folder of this session, not the user's ``~/.cache``."""
    before = os.environ.get("ORBITCT_CACHE_DIR")
    os.environ["ORBITCT_CACHE_DIR"] = str(tmp_path_factory.mktemp("cache"))
    yield
    if before is None:
        os.environ.pop("ORBITCT_CACHE_DIR", None)
    else:
        os.environ["ORBITCT_CACHE_DIR"] = before


@pytest.fixture(scope="module", autouse=True)
def _stop_sim_twins() -> Iterator[None]:
    """After each module: stop the in-process twins and collect garbage now. CPython 3.11.7's
    ast.parse fails with 'AST constructor recursion depth mismatch' when a finalizer runs Python code in
    the middle of it (gh-106905, fixed in 3.11.8); left-over asyncio objects would otherwise be finalised
    during a later test such as the layering check."""
    yield
    from devices.sim import stop_twins

    stop_twins()
    gc.collect()


@pytest.fixture(autouse=True)
def _bench_priority(request: pytest.FixtureRequest) -> Iterator[None]:
    """Tests marked ``realtime`` run at the bench's priority, as ``orbitct scan`` and the service's bench process
    do: a continuous sweep does not wait for a process starved by other work on the machine. The other test process
    runs at nice 0, not at the +5 of a lab's jobs (JOB_NICE), so a real-time test goes that much further (-10) to keep the
    same gap of 10 (subprocesses the tests start keep the priorities a user's commands have)."""
    if request.node.get_closest_marker("realtime") is None:
        yield
        return
    from acquire.priority import BENCH_NICE, JOB_NICE, bench_priority

    with bench_priority(BENCH_NICE - JOB_NICE):
        yield
