"""The documentation: the README as a front door, the site built in strict mode, generated reference pages that
miss nothing, pages that render offline in a real browser, and the REST example that the CI tutorial shows."""

from __future__ import annotations

import html
import json
import os
import re
import subprocess
import sys
import threading
from collections.abc import Iterator
from functools import partial
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import pytest

from acquire.config import BenchConfig, CArmConfig
from orbitct_app import reference_pages
from orbitct_app.cli.main import cli
from orbitct_app.service.core.settings import ServiceSettings
from tests.helpers.browser import chromium
from tests.helpers.service import serve_subprocess, small_bench_config

ROOT = Path(__file__).resolve().parents[2]


def test_the_readme_is_a_front_door() -> None:
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    assert len(text.splitlines()) <= 250
    for heading in ("## Who it is for", "## Two commands", "## The pipeline in one tour", "## Headline figures"):
        assert heading in text, heading
    for target in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", text):
        if not target.startswith(("http://", "https://")):
            assert (ROOT / target).exists(), f"the README links to {target}, which does not exist"


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The documentation site, built as CI builds it: strict, so a warning or a broken link fails it."""
    out = tmp_path_factory.mktemp("site")
    done = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(out)],
        cwd=ROOT,
        env={**os.environ, "NO_MKDOCS_2_WARNING": "1"},
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    return out


def page_text(site: Path, page: str) -> str:
    """A built page's text, tags removed."""
    return html.unescape(re.sub(r"<[^>]+>", "", (site / page).read_text(encoding="utf-8")))


@pytest.mark.system
def test_the_cli_reference_has_every_command_and_option(site: Path) -> None:
    text = page_text(site, "reference/cli.html")
    for path, command in reference_pages.walk_commands(cli):
        assert " ".join(path) in text, path
        for param in command.params:
            names = [param.name.upper()] if param.param_type_name == "argument" and param.name else param.opts
            for name in names:
                assert name in text, (path, name)


@pytest.mark.system
def test_the_rest_reference_has_every_route_and_schema(site: Path) -> None:
    text = page_text(site, "reference/rest-api.html")
    document = reference_pages.openapi_document()
    for route, operations in document["paths"].items():
        for method in operations:
            assert f"{method.upper()} {route}" in text, (method, route)
    for name, schema in document["components"]["schemas"].items():
        assert name in text, name
        for field in schema.get("properties", {}):
            assert field in text, (name, field)


@pytest.mark.system
def test_the_configuration_reference_has_every_key(site: Path) -> None:
    text = page_text(site, "reference/configuration.html")
    for model in (BenchConfig, CArmConfig, ServiceSettings):
        for key, _, _ in reference_pages.config_keys(model):
            assert key in text, (model.__name__, key)


class _QuietHandler(SimpleHTTPRequestHandler):
    def log_message(self, format: str, *args: object) -> None:
        pass


@pytest.fixture
def served(site: Path) -> Iterator[str]:
    """The built site on a loopback port, as `mkdocs serve` or any static web server would serve it."""
    server = ThreadingHTTPServer(("127.0.0.1", 0), partial(_QuietHandler, directory=str(site)))
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}"
    finally:
        server.shutdown()
        server.server_close()


@pytest.mark.system
def test_pages_render_offline_with_their_navigation(served: str) -> None:
    outside: list[str] = []
    with chromium() as browser:
        page = browser.new_page()

        def only_local(route, request) -> None:  # type: ignore[no-untyped-def]
            if request.url.startswith(served):
                route.continue_()
            else:
                outside.append(request.url)
                route.abort()

        page.route("**/*", only_local)
        for path, heading in (
            ("index.html", "orbitct"),
            ("tutorials/lab-technician.html", "Tutorial: the lab technician"),
            ("reference/cli.html", "Command line"),
        ):
            page.goto(f"{served}/{path}")
            assert page.locator("article h1").first.inner_text().strip().startswith(heading), path
            nav = page.locator("nav.md-nav--primary")
            assert nav.count() >= 1, path
            for section in ("Tutorials", "How-to guides", "Reference", "Explanation"):
                assert nav.first.get_by_text(section, exact=True).count() >= 1, (path, section)
            assert page.locator("link[rel=stylesheet]").count() >= 1, path
            assert page.evaluate("getComputedStyle(document.querySelector('.md-header')).position") in (
                "sticky",
                "fixed",
            ), f"{path}: the theme's styles were not applied"
    assert not outside, f"the site asked for outside resources: {outside}"


@pytest.mark.system
def test_the_rest_example_of_the_ci_tutorial_runs(tmp_path: Path) -> None:
    token = "oct_docs_example_token_0001"
    proc, base, _ = serve_subprocess(small_bench_config(tmp_path), tmp_path / "data", token)
    try:
        done = subprocess.run(
            [sys.executable, str(ROOT / "docs" / "examples" / "rest_scan_calibrate_reconstruct.py")],
            cwd=tmp_path,
            env={**os.environ, "ORBITCT_URL": base, "ORBITCT_TOKEN": token},
            capture_output=True,
            text=True,
            timeout=600,
        )
    finally:
        proc.terminate()
        proc.wait(timeout=60)
    assert done.returncode == 0, done.stdout + done.stderr[-3000:]
    assert "quality passed: True" in done.stdout
    assert (tmp_path / "axial.png").stat().st_size > 1000


@pytest.mark.system
def test_the_performance_page_shows_every_recorded_benchmark(site: Path) -> None:
    text = page_text(site, "explanation/performance.html")
    recorded = sorted((ROOT / "benchmarks" / "results").glob("*.json"))
    assert recorded, "no benchmark output is recorded in benchmarks/results/"
    for path in recorded:
        result = json.loads(path.read_text(encoding="utf-8"))
        assert result["command"] in text, path.name
        assert result["output"].splitlines()[-1].strip() in text, path.name
