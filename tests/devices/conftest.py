"""Shared fixtures for device tests: GCS twins on loopback sockets and connected drivers."""

from __future__ import annotations

import uuid
from collections.abc import AsyncIterator, Iterator

import pytest

from devices.hexapod import Hexapod
from devices.rotation_stage import RotationStage
from devices.twins.gcs import start_twin
from devices.twins.runtime import TwinThread
from devices.twins.world import SimWorld, get_world


@pytest.fixture
def anyio_backend() -> str:
    return "asyncio"


@pytest.fixture
def world_name() -> str:
    """A private simulated world per test."""
    return f"test-{uuid.uuid4().hex[:10]}"


@pytest.fixture
def world(world_name: str) -> SimWorld:
    return get_world(world_name)


@pytest.fixture
def hexapod_twin(world_name: str) -> Iterator[TwinThread]:
    server = start_twin("hexapod", world=world_name, time_scale=100.0)
    yield server
    server.stop()


@pytest.fixture
def stage_twin(world_name: str) -> Iterator[TwinThread]:
    server = start_twin("rotation_stage", world=world_name, time_scale=100.0)
    yield server
    server.stop()


@pytest.fixture
async def hexapod(hexapod_twin: TwinThread) -> AsyncIterator[Hexapod]:
    dev = Hexapod("hexapod", hexapod_twin.uri, timeout_s=1.0, move_timeout_s=5.0)
    await dev.connect()
    yield dev
    await dev.close()


@pytest.fixture
async def ready_hexapod(hexapod: Hexapod) -> Hexapod:
    await hexapod.reference()
    return hexapod


@pytest.fixture
async def stage(stage_twin: TwinThread) -> AsyncIterator[RotationStage]:
    dev = RotationStage("stage", stage_twin.uri, timeout_s=1.0, move_timeout_s=5.0)
    await dev.connect()
    yield dev
    await dev.close()
