"""A service on real controllers (standalone twins on TCP/Modbus ports, not ``--sim``): what a lab meets first."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
import yaml

from tests.app.service.conftest import Api
from tests.helpers.service import small_bench_config
from tests.helpers.twin_bench import TwinBench, twin_bench

pytestmark = [pytest.mark.timeout(180), pytest.mark.system]
SCAN = {"orbit": "sawtooth", "params": {"n_frames": 8, "amplitude_deg": 5.0}, "errors": "none"}


@pytest.fixture
def bench_api(make_api: Callable[..., Api], tmp_path: Path) -> Iterator[tuple[Api, TwinBench]]:
    with twin_bench("service-real", size=64) as twins:
        (tmp_path / "lab").mkdir()
        path = small_bench_config(tmp_path / "lab", size=64)
        cfg = yaml.safe_load(path.read_text())
        cfg["devices"] = {k: str(v) for k, v in twins.config.devices.model_dump().items()}
        path.write_text(yaml.safe_dump(cfg))
        yield make_api(bench_config=path, sim=False, dev_token=None), twins


def test_scan_on_unreferenced_axes_is_refused_until_referenced(bench_api: tuple[Api, TwinBench]) -> None:
    api, _ = bench_api
    r = api.post("/scans", json=SCAN)
    assert r.status_code == 409, r.text  # the bench's state, not the request, is in the way
    msg = r.json()["message"]
    assert "not referenced" in msg and "POST /devices/hexapod/reference" in msg and "nothing moved" in msg
    assert api.get("/scans").json() == []  # no scan recorded
    assert api.post("/scans/preflight", json=SCAN).status_code == 409
    for name in ("hexapod", "rotation_stage"):
        assert api.post(f"/devices/{name}/reference").status_code == 200
    r = api.post("/scans/preflight", json=SCAN)
    assert r.status_code == 200, r.text
