"""The service's small JSON files are written whole or not at all."""

from __future__ import annotations

import json
import stat
from pathlib import Path

import pytest

from orbitct_app.service.core.jsonfile import write_json_atomically


def test_written_whole_and_replaced(tmp_path: Path) -> None:
    path = tmp_path / "sub" / "state.json"
    write_json_atomically(path, {"a": 1})
    write_json_atomically(path, {"a": 2}, indent=None)
    assert json.loads(path.read_text()) == {"a": 2}
    assert [p.name for p in path.parent.iterdir()] == ["state.json"]  # no temporary file left


def test_private_file_is_its_owners_alone(tmp_path: Path) -> None:
    path = tmp_path / "tokens.json"
    write_json_atomically(path, [], private=True)
    assert stat.S_IMODE(path.stat().st_mode) == 0o600


def test_a_failed_write_keeps_the_old_file_and_leaves_no_temporary(tmp_path: Path) -> None:
    path = tmp_path / "estop.json"
    write_json_atomically(path, {"latched": True})
    with pytest.raises(TypeError):
        write_json_atomically(path, {"latched": object()})  # fails half-way through the dump
    assert json.loads(path.read_text()) == {"latched": True}
    assert [p.name for p in tmp_path.iterdir()] == ["estop.json"]
