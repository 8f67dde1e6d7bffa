"""Fixtures: a service on the simulated bench (twins), with one token per role."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml
from fastapi.testclient import TestClient

from orbitct_app.service.app import create_app
from orbitct_app.service.core.auth import create_token
from orbitct_app.service.core.settings import load_settings
from tests.helpers.service import small_bench_config


class Api:
    """A TestClient plus one bearer token per role."""

    def __init__(self, client: TestClient, tokens: dict[str, str], data_dir: Path) -> None:
        self.client, self.tokens, self.data_dir = client, tokens, data_dir
        self.service = client.app.state.service  # type: ignore[attr-defined]

    def headers(self, role: str | None) -> dict[str, str]:
        return {"Authorization": f"Bearer {self.tokens[role]}"} if role else {}

    def request(self, method: str, path: str, role: str | None = "operator", **kwargs: Any) -> Any:
        return self.client.request(method, path, headers={**self.headers(role), **kwargs.pop("headers", {})}, **kwargs)

    def get(self, path: str, role: str | None = "viewer", **kwargs: Any) -> Any:
        return self.request("GET", path, role, **kwargs)

    def post(self, path: str, role: str | None = "operator", **kwargs: Any) -> Any:
        return self.request("POST", path, role, **kwargs)


def _open(folder: Path, data: Path, opened: list[TestClient], **overrides: Any) -> Api:
    tokens_file = data / "tokens.json"
    if not tokens_file.exists():
        tokens = {role: create_token(tokens_file, role, f"test-{role}") for role in ("operator", "analyst", "viewer")}  # type: ignore[arg-type]
        (data / "test-tokens.yaml").write_text(yaml.safe_dump(tokens))
    tokens = yaml.safe_load((data / "test-tokens.yaml").read_text())
    settings = load_settings(
        None,
        **{
            "bench_config": small_bench_config(folder),
            "sim": True,
            "data_dir": data,
            "dev_token": "oct_dev_token_for_tests_only",
            "stop_port": 0,
            **overrides,
        },
    )
    tokens["dev"] = settings.dev_token
    client = TestClient(create_app(settings), raise_server_exceptions=False)
    client.__enter__()
    opened.append(client)
    return Api(client, tokens, data)


def _close_all(opened: list[TestClient]) -> None:
    for client in reversed(opened):
        client.__exit__(None, None, None)


@pytest.fixture
def make_api(tmp_path: Path) -> Iterator[Callable[..., Api]]:
    """Start a service (sim) in ``tmp_path``; call again with the same data dir to simulate a restart."""
    opened: list[TestClient] = []
    yield lambda data_dir=None, **overrides: _open(tmp_path, data_dir or tmp_path / "data", opened, **overrides)
    _close_all(opened)


@pytest.fixture
def api(make_api: Callable[..., Api]) -> Api:
    """A fresh running service with tokens for every role."""
    return make_api()


@pytest.fixture(scope="module")
def shared_api(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Api]:
    """One running service for a whole test module (tests that leave no state that matters)."""
    folder = tmp_path_factory.mktemp("shared")
    opened: list[TestClient] = []
    yield _open(folder, folder / "data", opened)
    _close_all(opened)
