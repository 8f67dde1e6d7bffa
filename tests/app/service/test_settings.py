"""Typed settings: defaults < YAML file < environment < command line; bad values refused with the field."""

from __future__ import annotations

from pathlib import Path

import pytest
from pydantic import ValidationError

from orbitct_app.service.core.settings import load_settings


def test_sources_in_order(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    f = tmp_path / "service.yaml"
    f.write_text("port: 9001\nhost: 0.0.0.0\njob_workers: 2\ndata_dir: /srv/orbitct\n")
    s = load_settings(f)
    assert (s.port, s.host, s.job_workers, s.data_dir) == (9001, "0.0.0.0", 2, Path("/srv/orbitct"))
    monkeypatch.setenv("ORBITCT_PORT", "9002")
    assert load_settings(f).port == 9002
    assert load_settings(f, port=9003).port == 9003
    assert load_settings(f, port=None).port == 9002  # an option not given does not override
    assert load_settings(f).tokens_path == Path("/srv/orbitct/tokens.json")


def test_bad_values_name_the_field(tmp_path: Path) -> None:
    f = tmp_path / "service.yaml"
    f.write_text("port: 70000\n")
    with pytest.raises(ValidationError, match="port"):
        load_settings(f)
    f.write_text("tokens: [{sha256: abc, role: admin}]\n")
    with pytest.raises(ValidationError, match="sha256|role"):
        load_settings(f)
    f.write_text("colour: blue\n")
    with pytest.raises(ValidationError, match="colour"):
        load_settings(f)
    for text, match in (
        ("dask_scheduler: localhost:8786", "dask_scheduler"),  # an address needs its protocol
        ("pacs_nodes: {lab: 'http://pacs:104'}", "dicom://AE_TITLE@host:port"),
        ("pacs_nodes: {'bad name!': 'dicom://PACS@pacs:104'}", "PACS node name"),
    ):
        f.write_text(text + "\n")
        with pytest.raises(ValidationError, match=match):
            load_settings(f)
    f.write_text("dask_scheduler: tcp://lab-cluster:8786\n")
    assert load_settings(f).dask_scheduler == "tcp://lab-cluster:8786"
