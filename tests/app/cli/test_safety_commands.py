"""``orbitct stop``, ``reset`` and ``reset-fault`` against a running ``orbitct serve --sim``; ``orbitct scan`` refuses
while the service's stop is latched."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
import yaml
from click.testing import CliRunner

from orbitct_app.cli.main import cli
from orbitct_app.service.core.auth import create_token
from tests.helpers.service import free_port, serve_subprocess, small_bench_config

pytestmark = [pytest.mark.system, pytest.mark.timeout(300)]
DEV = "oct_dev_token_for_cli_safety_test"


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, object]]:
    folder = tmp_path_factory.mktemp("cli-safety")
    data = folder / "data"
    tokens = {role: create_token(data / "tokens.json", role, f"cli-{role}") for role in ("operator", "viewer")}  # type: ignore[arg-type]
    config = small_bench_config(folder)
    proc, base, headers = serve_subprocess(config, data, DEV)
    stop_url = httpx.get(f"{base}/stop", headers=headers).json()["stop_url"]
    try:
        yield {"base": base, "stop_url": stop_url, "tokens": tokens, "data": data, "config": config, "folder": folder}
    finally:
        proc.terminate()
        proc.wait(60)


def _run(*args: str) -> tuple[int, str]:
    result = CliRunner().invoke(cli, list(args))
    return result.exit_code, result.output


def test_stop_latches_scan_refuses_and_only_an_operator_resets(service: dict) -> None:  # type: ignore[type-arg]
    base, tokens = service["base"], service["tokens"]
    code, out = _run(
        "stop", "--url", base, "--stop-url", service["stop_url"], "--token", tokens["viewer"], "--reason", "drill"
    )
    assert code == 0 and out.startswith("HALTED (latched; halted and verified"), out
    assert "xray: ok - high voltage off" in out

    scan = [
        "scan",
        "--config",
        str(service["config"]),
        "--sim",
        "--out",
        str(service["folder"] / "s.h5"),
        "--frames",
        "4",
        "--data-dir",
        str(service["data"]),
    ]
    code, out = _run(*scan)
    assert code == 2 and "emergency stop latched by cli-viewer (viewer)" in out and "scans refused" in out, out
    assert not (service["folder"] / "s.h5").exists()

    code, out = _run("reset", "--url", base, "--token", tokens["viewer"])
    assert code == 2 and "403" in out and "reset" in out, out
    code, out = _run("reset", "--url", base, "--token", tokens["operator"], "--note", "drill over")
    assert code == 0 and "reset by cli-operator (operator)" in out, out
    code, out = _run("reset", "--url", base, "--token", tokens["operator"])
    assert code == 2 and "not latched" in out


def test_stop_falls_back_to_the_service_when_the_listener_is_not_there(service: dict) -> None:  # type: ignore[type-arg]
    base, tokens = service["base"], service["tokens"]
    code, out = _run(
        "stop", "--url", base, "--stop-url", f"http://127.0.0.1:{free_port()}/stop", "--token", tokens["viewer"]
    )
    assert code == 0 and "not reachable" in out and "HALTED" in out, out
    assert _run("reset", "--url", base, "--token", tokens["operator"])[0] == 0


def test_stop_says_plainly_when_nothing_answers() -> None:
    port = free_port()
    code, out = _run("stop", "--url", f"http://127.0.0.1:{port}", "--token", "oct_x")
    assert code == 2 and "no stop delivered" in out and "stop the bench by hand" in out


def test_reset_fault_of_a_healthy_generator_and_of_a_device_without_faults(service: dict) -> None:  # type: ignore[type-arg]
    base, tokens = service["base"], service["tokens"]
    code, out = _run("reset-fault", "xray", "--url", base, "--token", tokens["operator"])
    assert code == 0 and "state IDLE, fault NONE" in out, out
    code, out = _run("reset-fault", "hexapod", "--url", base, "--token", tokens["operator"])
    assert code == 2 and "no fault to reset" in out, out
    code, out = _run("reset-fault", "xray", "--url", base, "--token", tokens["viewer"])
    assert code == 2 and "403" in out


def test_settings_file_names_the_stop_port(tmp_path: Path) -> None:
    from orbitct_app.service.core.settings import load_settings

    path = tmp_path / "service.yaml"
    path.write_text(yaml.safe_dump({"port": 9000}))
    assert load_settings(path).stop_port is None  # the guard then listens on 9001
    assert load_settings(path, stop_port=9100).stop_port == 9100
