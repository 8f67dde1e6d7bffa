"""The web console in real headless Chromium on the simulated bench: a technician's whole session, the emergency
stop, a viewer who is offered nothing that changes the bench, the API docs offline; screenshots of every page go to
``test-artefacts/console/``."""

from __future__ import annotations

import re
import time
from collections.abc import Iterator
from typing import Any

import httpx
import pytest

from orbitct_app.service.core.auth import create_token
from tests.helpers.browser import chromium
from tests.helpers.service import ROOT, SMALL_SAWTOOTH, ended, serve_subprocess, small_bench_config

pytestmark = [pytest.mark.system, pytest.mark.slow]
SHOTS = ROOT / "test-artefacts" / "console"
TIMEOUT_MS = 180_000


class Console:
    """The service under test: its URL, a token per role, and the API for checking what the pages claim."""

    def __init__(self, base: str, tokens: dict[str, str], browser: Any) -> None:
        self.base, self.tokens, self.browser = base, tokens, browser
        self.outside: list[str] = []  # every request a page made to anything but orbitct

    def api(self, method: str, path: str, role: str = "operator", **kwargs: Any) -> httpx.Response:
        return httpx.request(
            method, self.base + path, headers={"Authorization": f"Bearer {self.tokens[role]}"}, timeout=30, **kwargs
        )

    def sign_in(self, role: str, viewport: tuple[int, int] = (1280, 800), token: str | None = None) -> Any:
        """A new browser context (its own cookies) signed in as ``role`` (or with ``token``); on the bench page."""
        context = self.browser.new_context(viewport={"width": viewport[0], "height": viewport[1]})
        page = context.new_page()
        page.set_default_timeout(30_000)
        page.on(
            "request", lambda r: None if r.url.startswith((self.base, "data:", "blob:")) else self.outside.append(r.url)
        )
        page.goto(self.base + "/")
        assert "/sign-in" in page.url, page.url
        page.fill("#token", token or self.tokens[role])
        page.click("#sign-in-form button[type=submit]")
        page.wait_for_url("**/console/bench")
        page.wait_for_selector("[data-device]")
        return page


def until(page: Any, predicate: str, timeout_s: float = 30.0) -> None:
    """Poll a function in the page (``wait_for_function`` evaluates a string, which the pages' policy forbids)."""
    t0 = time.monotonic()
    while not page.evaluate(predicate):
        assert time.monotonic() - t0 < timeout_s, f"not true after {timeout_s} s: {predicate}"
        time.sleep(0.1)


def shot(page: Any, name: str) -> None:
    SHOTS.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=str(SHOTS / f"{name}.png"), full_page=True)


@pytest.fixture(scope="module")
def console(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Console]:
    folder = tmp_path_factory.mktemp("console")
    data = folder / "data"
    data.mkdir()
    tokens = {
        role: create_token(data / "tokens.json", role, f"tech-{role}") for role in ("operator", "analyst", "viewer")
    }  # type: ignore[arg-type]
    # 256 px: at 192 px a 30-frame sawtooth's BBs are ~2 px wide and 1 noise draw in 12 fails the calibration's
    # quality check; at 256 px all 12 pass with the worst view predicted at 0.15-0.24 px
    proc, base, _ = serve_subprocess(small_bench_config(folder, size=256), data, "oct_dev_console_tests_only")
    try:
        with chromium() as browser:
            yield Console(base, tokens, browser)
    finally:
        proc.terminate()
        proc.wait(30)


def _scan(page: Any, console: Console, frames: int, live: bool = False) -> str:
    page.goto(console.base + "/console/scans/new")
    page.select_option("#orbit", "sawtooth")
    page.fill("#param-amplitude_deg", "6")
    page.fill("#param-cycles", "2")
    page.fill("#frames", str(frames))
    page.fill("#scan-name", f"console test {frames}")
    if live:
        page.check("#calibrate-live")
    else:
        page.fill("#frame-rate", "20")
    from playwright.sync_api import expect

    # the page reads the detector from the service after it loads: wait for it, do not race it
    expect(page.locator("#detector")).to_contain_text("tube voltage (kV)", timeout=TIMEOUT_MS)
    page.click("#check")
    page.wait_for_selector("#preflight.yes")
    assert "within the limits" in page.inner_text("#preflight")
    assert page.is_visible("#preview")
    shot(page, "new-scan")
    page.click("#start")
    page.wait_for_url(re.compile(r".*/console/scans/[0-9a-f]{16}$"))
    return str(page.url.rsplit("/", 1)[1])


def test_a_whole_session_scan_calibrate_reconstruct_view_and_stop(console: Console) -> None:
    from playwright.sync_api import expect

    # operator: a short scan, watched to the end
    page = console.sign_in("operator")
    shot(page, "bench")
    scan_id = first_scan = _scan(page, console, 40)
    expect(page.locator("#scan-progress-text")).to_contain_text("frame", timeout=TIMEOUT_MS)
    expect(page.locator("#scan-state")).to_have_text("complete", timeout=TIMEOUT_MS)
    expect(page.locator("#scan-progress-text")).to_contain_text(
        "of 46"
    )  # 40 projections, 4 darks and flats before, 2 after
    expect(page.locator("#scan-progress-text")).to_contain_text(" in all")  # how long it said its frames take
    # the same counts, named, on the scan page and in the scan list (the views a calibration counts: 40)
    expect(page.locator("#scan-facts dt:has-text('frames') + dd")).to_have_text(
        "46 of 46 (40 projections, 6 darks and flats)", timeout=TIMEOUT_MS
    )
    assert console.api("GET", f"/scans/{scan_id}").json().get("state") == "complete", console.api(
        "GET", f"/scans/{scan_id}"
    ).text
    shot(page, "scan-complete")
    # the twins read back what was commanded: the summary says no projection was taken off command, not a blank
    expect(page.locator("#scan-summary dt:has-text('taken off command') + dd")).to_have_text("none")
    assert page.locator("#calibrate-form").count() == 0, "an operator does not calibrate"
    page.click("#sign-out")
    page.wait_for_url("**/sign-in")
    page.context.close()

    # analyst: calibration and its report, FDK with the calibrated and the nominal geometry, the viewer
    page = console.sign_in("analyst")
    page.goto(f"{console.base}/console/scans/{scan_id}")
    page.click("#calibrate")
    rows = page.locator("#scan-jobs tbody tr")
    expect(rows).to_have_count(1)
    expect(rows.first).to_contain_text("succeeded", timeout=TIMEOUT_MS)
    page.fill("#rec-shape", "48")
    page.click("#reconstruct")
    expect(rows).to_have_count(2)
    page.select_option("#rec-geometry", "nominal")
    page.fill("#rec-shape", "32")  # coarser voxels: the viewer compares the two on one grid
    page.click("#reconstruct")
    expect(rows).to_have_count(3)
    for i in range(3):
        expect(rows.nth(i)).to_contain_text("succeeded", timeout=TIMEOUT_MS)
    shot(page, "scan-with-jobs")
    assert page.locator("#scan-jobs a", has_text="viewer").count() == 2
    page.click("#scan-jobs >> text=report")
    expect(page.locator("#table1")).to_be_visible()
    expect(page.locator("#verdict-text")).not_to_be_empty()
    expect(page.locator("#figures img")).to_have_count(3)  # the RPE violins, the corrections, the worst view
    assert page.locator("#iterations tbody tr").count() >= 2
    until(page, "() => Array.from(document.images).every((i) => i.complete && i.naturalWidth > 0)")
    shot(page, "calibration-report")
    page.go_back()
    calibrated = next(
        j
        for j in console.api("GET", f"/reconstructions?scan_id={scan_id}").json()
        if j["params"]["geometry"] == "calibrated"
    )
    page.goto(f"{console.base}/console/reconstructions/{calibrated['id']}")
    page.wait_for_selector("body[data-viewer-ready]", timeout=60_000)
    assert page.get_attribute("body", "data-viewer-ready") == "yes", "WebGL2 (SwiftShader) runs the 3-D viewer"
    assert page.is_visible("#pane-b") and "nominal geometry" in page.inner_text("#caption-b")
    # volumes of different voxel sizes side by side: the nominal one resampled onto the calibrated one's grid
    assert "resampled onto the first volume's grid" in page.inner_text("#caption-b")
    own_grid = page.get_attribute("#gl-a >> xpath=ancestor::figure", "data-grid")
    assert own_grid and own_grid.startswith("48 x 48 x 48 voxels")
    assert page.get_attribute("#pane-b", "data-grid") == own_grid
    for bar in ("#scale-a", "#scale-b"):  # a labelled scale bar in mm on each
        expect(page.locator(f"{bar} .label")).to_have_text(re.compile(r"^\d+(\.\d+)? mm$"))
        width = page.locator(f"{bar} .bar").bounding_box()
        assert width is not None and width["width"] > 20, width
    assert page.inner_text("#scale-a .label") == page.inner_text("#scale-b .label")  # the same scale on both
    nifti = page.get_attribute("#download-nifti", "href")
    assert (
        httpx.get(console.base + nifti, headers={"Authorization": f"Bearer {console.tokens['viewer']}"}).content[:2]
        == b"\x1f\x8b"
    )
    page.fill("#wmin", "0")
    page.fill("#wmax", "0.03")
    page.dispatch_event("#wmax", "change")
    windows = page.evaluate("() => [document.getElementById('wmin').value, document.getElementById('wmax').value]")
    assert windows == ["0", "0.03"]
    time.sleep(1.0)
    shot(page, "viewer")
    page.select_option("#view", "3d")
    time.sleep(1.0)
    shot(page, "viewer-3d")
    page.goto(console.base + "/console/jobs")
    expect(page.locator("#job-table tbody tr")).to_have_count(3)
    page.locator("#job-table button", has_text="Log").first.click()
    expect(page.locator("#job-log pre")).not_to_be_empty()
    shot(page, "jobs")
    # a browser without WebGL2: the middle slices as pictures, the second volume's on the first one's grid
    page.add_init_script("HTMLCanvasElement.prototype.getContext = function () { return null; };")
    page.goto(f"{console.base}/console/reconstructions/{calibrated['id']}")
    page.wait_for_selector("body[data-viewer-ready]", timeout=60_000)
    assert page.get_attribute("body", "data-viewer-ready") == "fallback"
    expect(page.locator("#pane-b figcaption")).to_contain_text("resampled onto")
    pictures = page.locator("#pane-b img")
    expect(pictures).to_have_count(3)
    assert all("grid_of=" in (pictures.nth(i).get_attribute("src") or "") for i in range(3))
    until(page, "() => Array.from(document.images).every((i) => i.complete && i.naturalWidth > 0)")
    shot(page, "viewer-fallback")
    page.context.close()

    # operator again: a long scan, stopped with the emergency stop (the key Esc) while it runs
    page = console.sign_in("operator")
    scan_id = _scan(page, console, 2000, live=True)
    expect(page.locator("#scan-progress-text")).to_contain_text("frame", timeout=60_000)
    until(page, "() => document.getElementById('scan-progress').value >= 5", 60.0)
    # the latest frame is drawn, with the BBs the live calibration found in it
    expect(page.locator("#frame-caption")).to_contain_text("BBs detected", timeout=60_000)
    # and the running RPE and the predicted error of the frames' geometry, once the BBs are followed in 3-D
    expect(page.locator("#live-calibration-text")).to_contain_text("predicted error", timeout=60_000)
    shot(page, "scan-live")
    # a reload mid-scan: the page picks the stream up again and the count goes on
    before = page.evaluate("() => document.getElementById('scan-progress').value")
    page.reload()
    until(page, f"() => document.getElementById('scan-progress').value > {before}", 60.0)
    page.keyboard.press("Escape")
    expect(page.locator("#stop-result")).to_contain_text("Stopped and verified", timeout=30_000)
    expect(page.locator("#latch")).to_be_visible()
    expect(page.locator("#scan-state")).to_have_text("aborted", timeout=30_000)
    shot(page, "emergency-stop")
    scan = console.api("GET", f"/scans/{scan_id}").json()
    assert ended(scan) and scan["state"] == "aborted" and "emergency stop" in scan["reason"]
    xray = console.api("GET", "/devices/xray").json()["state"]
    assert xray["hv_on"] is False and xray["exposing"] is False
    for motion in ("hexapod", "rotation_stage"):
        moving = console.api("GET", f"/devices/{motion}").json()["state"]["moving"]
        assert not any(moving.values()) if isinstance(moving, dict) else moving is False, (motion, moving)
    # the latch holds until an operator resets it, from the banner on any page
    page.goto(console.base + "/console/scans")
    expect(page.locator("#latch")).to_be_visible()
    page.fill("#reset-note", "checked the bench")
    page.click("#reset-stop")
    expect(page.locator("#latch")).to_be_hidden()
    assert console.api("GET", "/stop").json()["latched"] is False
    listed = page.locator("#scan-table tbody tr", has_text=first_scan)
    expect(listed).to_contain_text("46 / 46 (40 projections, 6 darks and flats)")  # as on the scan page
    stopped = page.locator("#scan-table tbody tr", has_text=scan_id).inner_text()  # the frames it kept, named
    done, _, views, dark_flat = (
        int(n) for n in re.findall(r"(\d+) / (\d+) \((\d+) projections, (\d+) darks", stopped)[0]
    )
    assert done == views + dark_flat, stopped
    shot(page, "scans")
    page.context.close()
    assert not console.outside, f"pages fetched from outside orbitct: {console.outside}"


def _ended(console: Console, path: str, timeout_s: float = 180.0) -> dict[str, Any]:
    t0 = time.monotonic()
    while not ended(body := console.api("GET", path).json()):
        assert time.monotonic() - t0 < timeout_s, body
        time.sleep(0.2)
    return body


def _not_green(page: Any, selector: str) -> None:
    """The element says failed and is drawn red, not in the console's green."""
    element = page.locator(selector).first
    assert "failed" in element.inner_text(), element.inner_text()
    colours = element.evaluate("(e) => [getComputedStyle(e).color, getComputedStyle(e).backgroundColor]")
    assert not any(c in ("rgb(27, 122, 58)", "rgb(220, 242, 227)") for c in colours), colours


def test_a_failed_calibration_shows_failed_everywhere_and_blocks_reconstruction_until_overridden(
    console: Console,
) -> None:
    """A calibration whose quality check fails (here: a limit no geometry meets) is failed on the scan list, the
    scan page, the report, the jobs page; reconstructing from it is refused until asked for explicitly, and the
    volume then carries the override in the viewer."""
    from playwright.sync_api import expect

    r = console.api("POST", "/scans", json={**SMALL_SAWTOOTH, "frames": 40, "name": "failed check"})
    assert r.status_code == 202, r.text
    scan_id = r.json()["id"]
    assert _ended(console, f"/scans/{scan_id}")["state"] == "complete"
    r = console.api("POST", "/calibrations", role="analyst", json={"scan_id": scan_id, "max_predicted_px": 0.0001})
    cal = _ended(console, f"/calibrations/{r.json()['id']}")
    assert cal["state"] == "failed" and cal["verdict"]["status"] == "failed", cal
    assert "quality check failed" in cal["reason"] and "predicted error above 0.0001 px" in cal["reason"]
    assert cal["error"] == "failed_quality_check", cal
    refused = console.api("POST", "/reconstructions", role="analyst", json={"scan_id": scan_id, "shape": [32] * 3})
    assert refused.status_code == 409 and refused.json()["error"] == "failed_quality_check", refused.text
    assert '"accept_failed_geometry": true' in refused.json()["message"]

    page = console.sign_in("analyst")
    page.goto(console.base + "/console/scans")
    row = page.locator("#scan-table tbody tr", has_text=scan_id)
    expect(row.locator("[data-verdict]")).to_have_attribute("data-verdict", "failed", timeout=30_000)
    _not_green(page, f"#scan-table tbody tr:has-text('{scan_id}') [data-verdict]")
    shot(page, "failed-calibration-scans")

    page.goto(f"{console.base}/console/scans/{scan_id}")
    expect(page.locator("#scan-calibration [data-verdict]")).to_have_attribute("data-verdict", "failed")
    # the file's summary agrees: it was read again when the calibration ended
    expect(page.locator("#scan-summary dt:text-is('calibration') + dd")).to_contain_text("failed")
    expect(page.locator("#rec-failed-geometry")).to_be_visible()
    rows = page.locator("#scan-jobs tbody tr")
    expect(rows).to_have_count(1)
    _not_green(page, "#scan-jobs tbody tr [data-verdict]")
    page.fill("#rec-shape", "32")
    page.click("#reconstruct")  # refused: the failed geometry was not accepted
    expect(page.locator("#reconstruct-form .error")).to_contain_text("failed its quality check")
    expect(rows).to_have_count(1)
    shot(page, "failed-calibration-refused")
    page.check("#rec-accept-failed")
    page.click("#reconstruct")
    expect(rows).to_have_count(2)
    expect(rows.first).to_contain_text("succeeded", timeout=TIMEOUT_MS)
    expect(rows.first.locator("[data-verdict]")).to_have_attribute("data-verdict", "passed_with_warnings")
    shot(page, "failed-calibration-overridden")

    page.goto(f"{console.base}/console/calibrations/{cal['id']}")
    expect(page.locator("#verdict-badge [data-verdict]")).to_have_attribute("data-verdict", "failed")
    _not_green(page, "#job-state")
    expect(page.locator("#verdict-text")).to_contain_text("Do not use this geometry")
    expect(page.locator("#table1")).to_be_visible()  # the report is there to read why
    shot(page, "failed-calibration-report")

    page.goto(console.base + "/console/jobs")
    _not_green(page, f"#job-table tbody tr:has-text('{cal['id']}') [data-verdict]")

    volume = next(j for j in console.api("GET", f"/reconstructions?scan_id={scan_id}").json())
    assert volume["result"]["geometry_override"] is True and volume["verdict"]["status"] == "passed_with_warnings"
    page.goto(f"{console.base}/console/reconstructions/{volume['id']}")
    page.wait_for_selector("body[data-viewer-ready]", timeout=60_000)
    expect(page.locator("#verdict-a")).to_be_visible()
    expect(page.locator("#verdict-a")).to_contain_text("failed its quality check, by explicit override")
    _not_green(page, "#verdict-a")
    shot(page, "failed-calibration-viewer")
    page.context.close()


def test_an_operator_adds_a_technician_who_scans_calibrates_and_reconstructs_with_one_sign_in(
    console: Console,
) -> None:
    """People page: the operator adds a technician with the operator and analyst roles; with that one token the
    technician scans, calibrates and reconstructs; an analyst-only sign-in is told which role the bench needs."""
    from playwright.sync_api import expect

    page = console.sign_in("operator")
    page.click("header nav >> text=People")
    page.wait_for_url("**/console/people")
    page.fill("#person-name", "technician")
    page.check("#person-form input[value=operator]")
    page.check("#person-form input[value=analyst]")
    page.click("#add-person")
    expect(page.locator("#new-token .token")).to_have_text(re.compile(r"^oct_"))
    token = page.inner_text("#new-token .token")
    expect(page.locator("tr[data-person=technician]")).to_contain_text("operator, analyst")
    shot(page, "people")
    page.context.close()

    page = console.sign_in("operator", token=token)
    assert page.inner_text(".who .role") == "(operator, analyst)"
    scan_id = _scan(page, console, 30)
    expect(page.locator("#scan-state")).to_have_text("complete", timeout=TIMEOUT_MS)
    page.click("#calibrate")
    rows = page.locator("#scan-jobs tbody tr")
    expect(rows.first).to_contain_text("succeeded", timeout=TIMEOUT_MS)
    page.fill("#rec-shape", "32")
    page.click("#reconstruct")
    expect(rows).to_have_count(2)
    expect(rows.first).to_contain_text("succeeded", timeout=TIMEOUT_MS)
    shot(page, "technician-one-sign-in")
    assert page.locator("header nav >> text=People").count() == 1  # an operator, so may manage people
    page.context.close()

    refused = console.api("POST", "/scans", role="analyst", json={**SMALL_SAWTOOTH, "frames": 10}).json()
    assert refused["error"] == "forbidden" and "needs the operator role" in refused["message"], refused
    assert "tech-analyst is signed in as analyst" in refused["message"] and "scan" not in refused["message"][:40]
    assert console.api("DELETE", "/people/technician").status_code == 204
    assert console.api("GET", f"/scans/{scan_id}", role="viewer").status_code == 200


def test_the_bench_page_turns_its_controls_off_with_the_reason_while_the_stop_is_latched(console: Console) -> None:
    from playwright.sync_api import expect

    page = console.sign_in("operator")
    controls = page.locator(".device .reference:visible, .device form.move:visible button")
    expect(controls.first).to_be_enabled()
    # in the operator's terms: a named state per device, each axis with its unit and soft limits, no register values
    hexapod = page.locator('.device[data-device="hexapod"]')
    expect(hexapod.locator(".status")).to_have_text(re.compile(r"^(on target|referenced|not referenced)$"))
    expect(hexapod.locator("table.axes tbody tr")).to_have_count(6)
    expect(hexapod.locator("table.axes tbody tr").first).to_contain_text(" mm")
    expect(hexapod.locator("table.axes tbody tr").first).to_contain_text(re.compile(r"-?\d+ … -?\d+ mm"))
    xray = page.locator('.device[data-device="xray"]')
    expect(xray.locator(".status")).to_have_text(re.compile(r"^(standby|ready|door open)$"))
    expect(xray.locator("table.state")).to_contain_text("kV")
    expect(xray.locator("table.state")).not_to_contain_text("fault_code")
    assert console.api("POST", "/stop", json={"reason": "test of the bench page"}).status_code == 202
    expect(page.locator("#bench-gate")).to_contain_text("the emergency stop is latched", timeout=10_000)
    expect(hexapod.locator(".status")).to_have_text("latched", timeout=10_000)
    expect(xray.locator(".status")).to_have_text("latched")
    for i in range(controls.count()):
        expect(controls.nth(i)).to_be_disabled()
        assert "latched" in (controls.nth(i).get_attribute("title") or "")
    shot(page, "bench-latched")
    assert console.api("POST", "/stop/reset", json={"note": "bench page test"}).status_code == 200
    expect(page.locator("#bench-gate")).to_be_hidden(timeout=10_000)
    expect(controls.first).to_be_enabled()
    page.context.close()


def test_a_viewer_finds_no_controls_that_change_the_bench_and_the_api_refuses_them(console: Console) -> None:
    page = console.sign_in("viewer", viewport=(820, 1180))  # a tablet, upright
    stop = page.locator("#estop").bounding_box()
    assert stop is not None and stop["x"] >= 0 and stop["x"] + stop["width"] <= 820 and stop["y"] < 200, stop
    page.keyboard.press("Tab")  # keyboard reachable: the first stop is the skip link, then the navigation
    assert page.evaluate("document.activeElement.className") == "skip"
    shot(page, "tablet-bench")
    assert page.locator("button.reference").count() == 0 and page.locator("form.move").count() == 0
    assert page.locator("#reset-stop").count() == 0
    page.goto(console.base + "/console/scans/new")
    page.wait_for_selector("#orbit option", state="attached")
    assert page.locator("#start").count() == 0 and "may look at orbits but not start scans" in page.inner_text("main")
    # what the page does not offer, the API refuses even with the page's own session and CSRF token
    status = page.evaluate("""async () => {
        const csrf = document.querySelector('meta[name="csrf-token"]').content;
        const r = await fetch('/scans', {method: 'POST', headers: {'Content-Type': 'application/json', 'X-CSRF-Token': csrf},
                                         body: JSON.stringify({orbit: 'sawtooth', frames: 4})});
        return [r.status, (await r.json()).message];
    }""")
    assert status[0] == 403 and "viewer" in status[1]
    # ... and a cross-site form post (the cookie without the CSRF header) is refused too
    forged = page.evaluate("""async () => (await fetch('/devices/hexapod/reference', {method: 'POST'})).status""")
    assert forged == 403
    # the token never reaches the page or the URL
    assert console.tokens["viewer"] not in page.content() and console.tokens["viewer"] not in page.url
    shot(page, "viewer-new-scan")
    page.context.close()
    assert not console.outside, console.outside


def test_the_api_docs_render_with_no_internet(console: Console) -> None:
    context = console.browser.new_context(viewport={"width": 1280, "height": 800})
    page = context.new_page()
    blocked: list[tuple[str, str]] = []

    def offline(route: Any) -> None:  # a lab network without internet: only orbitct answers
        if route.request.url.startswith(console.base):
            route.continue_()
        else:
            blocked.append((route.request.resource_type, route.request.url))
            route.abort("internetdisconnected")

    page.route("**/*", offline)
    page.goto(console.base + "/docs")
    page.wait_for_selector(".swagger-ui .info .title", timeout=60_000)
    assert "orbitct" in page.inner_text(".swagger-ui .info .title")
    page.wait_for_selector(".opblock-tag-section")
    shot(page, "docs")
    page.goto(console.base + "/redoc")
    page.wait_for_selector("redoc h1", timeout=60_000)
    assert "orbitct" in page.inner_text("redoc h1")
    shot(page, "redoc")
    context.close()
    assert not [b for b in blocked if b[0] in ("script", "stylesheet", "font", "fetch", "xhr")], blocked
    # ReDoc's footer asks its CDN for a logo: the page's policy blocks it before any request leaves
    assert all(url == "https://cdn.redoc.ly/redoc/logo-mini.svg" for _, url in blocked), blocked


def test_an_analyst_plans_bbs_and_a_viewer_reads_the_plan(console: Console) -> None:
    page = console.sign_in("analyst")
    page.goto(console.base + "/console/plans")
    page.select_option("#plan-experiment", "A")
    page.fill("#plan-frames", "60")
    page.fill("#plan-bbs", "6")
    page.fill("#plan-detector", "192")
    page.fill("#plan-keep-out", "bad line")
    page.click("#plan-make")
    until(page, "() => document.querySelector('#plan-form .error').textContent.includes('FROM_DEG:TO_DEG')")
    page.fill("#plan-keep-out", "0:360,-500:500")  # the whole turn: nowhere left to tape a BB
    page.click("#plan-make")
    until(page, "() => document.querySelector('#plan-form .error').textContent.includes('cover the whole surface')")
    page.fill("#plan-keep-out", "300:60,-80:80")
    page.click("#plan-make")
    page.wait_for_selector("body[data-plan]", timeout=60_000)
    plan_id = page.evaluate("document.body.dataset.plan")
    assert page.locator("#plan-bbs-table tbody tr").count() == 6
    until(
        page,
        "() => document.getElementById('plan-picture').complete && document.getElementById('plan-picture').naturalWidth > 0",
    )
    angles = [float(page.inner_text(f"#plan-bbs-table tbody tr:nth-child({k}) td:nth-child(2)")) for k in range(1, 7)]
    assert all(60.0 < a < 300.0 for a in angles), angles  # outside the keep-out patch
    assert "the experiment's own placement" in page.inner_text("#plan-facts")
    until(page, f"() => document.querySelector('#plan-table').textContent.includes('{plan_id}')")
    shot(page, "bb-plan")
    # a plan of minutes is made in the background: the page says so, and it can be cancelled
    page.fill("#plan-keep-out", "")
    page.fill("#plan-frames", "2000")
    page.fill("#plan-detector", "768")
    page.fill("#plan-target", "0.001")
    page.click("#plan-make")
    page.wait_for_selector("#plan-progress:not([hidden])", timeout=30_000)
    long_id = page.inner_text("#plan-progress .id")
    until(
        page,
        f"() => [...document.querySelectorAll('#plan-table tr')].some((r) => r.textContent.includes('{long_id}') "
        "&& r.textContent.includes('planning'))",
    )
    until(page, "() => /of \\d+ \\(/.test(document.getElementById('plan-step').textContent)")  # how far it got
    shot(page, "bb-plan-planning")
    page.click("#plan-cancel")
    until(page, "() => document.querySelector('#plan-form .error').textContent.includes('cancelled by')")
    assert page.is_hidden("#plan-progress")
    until(
        page,
        f"() => [...document.querySelectorAll('#plan-table tr')].some((r) => r.textContent.includes('{long_id}') "
        "&& r.textContent.includes('cancelled'))",
    )
    page.context.close()
    viewer = console.sign_in("viewer")
    viewer.goto(console.base + f"/console/plans?plan={plan_id}")
    viewer.wait_for_selector("body[data-plan]")
    assert viewer.locator("#plan-form").count() == 0 and "may look at plans but not make them" in viewer.inner_text(
        "main"
    )
    assert viewer.locator("#plan-bbs-table tbody tr").count() == 6
    viewer.context.close()
    assert not console.outside, console.outside


def test_an_analyst_plans_bbs_on_a_reconstructions_surface_on_an_uploaded_mesh_and_on_a_shape(console: Console) -> None:
    """The form offers every succeeded reconstruction and every uploaded mesh as the object's real surface, uploads
    a mesh (a file that is no mesh is refused in one line), and takes a shape by parameters."""
    from playwright.sync_api import expect

    page = console.sign_in("operator")
    scan_id = _scan(page, console, 20)
    expect(page.locator("#scan-state")).to_have_text("complete", timeout=TIMEOUT_MS)
    page.context.close()
    job = console.api(
        "POST",
        "/reconstructions",
        role="analyst",
        json={"scan_id": scan_id, "algorithm": "fdk", "geometry": "nominal", "shape": [48, 48, 48]},
    ).json()
    deadline = time.monotonic() + TIMEOUT_MS / 1000
    while console.api("GET", f"/reconstructions/{job['id']}").json()["state"] != "succeeded":
        assert time.monotonic() < deadline, console.api("GET", f"/reconstructions/{job['id']}").json()
        time.sleep(0.2)
    page = console.sign_in("analyst")
    page.goto(console.base + "/console/plans")
    until(page, f"() => !!document.querySelector('#plan-surface option[value=\"reconstruction:{job['id']}\"]')")
    page.select_option("#plan-surface", f"reconstruction:{job['id']}")
    page.fill("#plan-frames", "60")
    page.fill("#plan-bbs", "6")
    page.fill("#plan-detector", "192")
    page.click("#plan-make")
    until(
        page,
        f"() => document.querySelector('#plan-facts').textContent.includes('outline of reconstruction {job['id']}')",
        timeout_s=60.0,
    )
    plan_id = page.evaluate("document.body.dataset.plan")
    plan = console.api("GET", f"/plans/bbs/{plan_id}").json()
    assert plan["surface"]["kind"] == "outline" and len(plan["bbs"]) == 6

    # a mesh of the object uploaded from the form becomes the surface chosen
    import trimesh

    stl = bytes(trimesh.creation.cylinder(radius=62.0, height=120.0, sections=96).export(file_type="stl"))
    page.set_input_files("#plan-mesh", files=[{"name": "bad.stl", "mimeType": "model/stl", "buffer": b"no mesh"}])
    until(page, "() => document.querySelector('#plan-form .error').textContent.includes(\"'bad.stl'\")")
    page.set_input_files("#plan-mesh", files=[{"name": "leg.stl", "mimeType": "model/stl", "buffer": stl}])
    until(page, "() => document.getElementById('plan-surface').value.startsWith('mesh:')")
    page.click("#plan-make")
    until(
        page, "() => document.querySelector('#plan-facts').textContent.includes('outline of leg.stl')", timeout_s=60.0
    )
    plan = console.api("GET", f"/plans/bbs/{page.evaluate('document.body.dataset.plan')}").json()
    assert plan["surface"]["source"] == "leg.stl" and len(plan["bbs"]) == 6

    # a shape by parameters: with a mesh still chosen, one line says to give one surface; alone, it is planned on
    page.fill("#plan-shape", "ellipsoid:70,60,90")
    page.click("#plan-make")
    until(
        page,
        "() => document.querySelector('#plan-form .error').textContent.includes('not surface_id and surface_shape')",
    )
    page.select_option("#plan-surface", "")
    page.click("#plan-make")
    until(
        page,
        "() => document.querySelector('#plan-facts').textContent.includes('ellipsoid 70 × 60 × 90 mm')",
        timeout_s=60.0,
    )
    page.context.close()
    assert not console.outside, console.outside
