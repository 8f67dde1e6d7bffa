"""Smoke test of an installed orbitct (run by .ci/wheel-check with the fresh environment's Python, outside the
checkout): `orbitct serve --sim` comes up, a person signs in to the console, scans, reconstructs, and the volume
viewer's page and its library are served."""

from __future__ import annotations

import hashlib
import json
import re
import subprocess
import sys
import threading
import time
import urllib.request
from http.cookiejar import CookieJar
from pathlib import Path

PORT = 8391
BASE = f"http://127.0.0.1:{PORT}"
opener = urllib.request.build_opener(urllib.request.HTTPCookieProcessor(CookieJar()))
csrf = ""


def call(method: str, path: str, body: object = None) -> tuple[int, bytes]:
    data = None if body is None else json.dumps(body).encode()
    request = urllib.request.Request(BASE + path, data=data, method=method)
    request.add_header("Content-Type", "application/json")
    if csrf:
        request.add_header("X-CSRF-Token", csrf)
    with opener.open(request, timeout=60) as answer:
        return answer.status, answer.read()


def connected() -> bool:
    try:
        return bool(json.loads(call("GET", "/health")[1])["bench"] == "connected")
    except OSError:  # not listening yet
        return False


def wait(path: str, timeout_s: float = 300.0) -> dict:
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout_s:
        state = json.loads(call("GET", path)[1])
        if state["state"] in {"complete", "aborted", "failed", "interrupted", "succeeded", "cancelled"}:
            return state
        time.sleep(1)
    sys.exit(f"{path} did not end within {timeout_s:.0f} s")


def main() -> None:
    global csrf
    serve = subprocess.Popen(
        [str(Path(sys.executable).parent / "orbitct"), "serve", "--sim", "--port", str(PORT), "--data-dir", "data"],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        token = ""
        assert serve.stdout is not None
        for line in serve.stdout:
            print("  serve:", line.rstrip())
            if found := re.search(r"\b(oct_\S+)", line):
                token = found.group(1)
            if "orbitct service on" in line:
                break
        assert token, "orbitct serve printed no development token"
        threading.Thread(target=lambda: [None for _ in serve.stdout], daemon=True).start()  # keep the pipe drained
        t0 = time.monotonic()
        while not connected():
            assert time.monotonic() - t0 < 120, "the simulated bench did not connect"
            time.sleep(1)
        from orbitct import __version__

        openapi = json.loads(call("GET", "/openapi.json")[1])
        assert openapi["info"]["version"] == __version__, (openapi["info"]["version"], __version__)
        status, page = call("GET", "/sign-in")
        assert status == 200 and b"orbitct" in page
        csrf = json.loads(call("POST", "/session", {"token": token})[1])["csrf_token"]
        for path in ("/console/bench", "/console/scans/new", "/console/scans", "/console/jobs", "/docs"):
            status, _ = call("GET", path)
            assert status == 200, (path, status)
        scan = json.loads(call("POST", "/scans", {"orbit": "circular", "frames": 24, "name": "wheel smoke"})[1])
        scan = wait(f"/scans/{scan['id']}")
        assert scan["state"] == "complete", scan
        job = json.loads(
            call(
                "POST",
                "/reconstructions",
                {"scan_id": scan["id"], "algorithm": "fdk", "geometry": "nominal", "shape": [32, 48, 48]},
            )[1]
        )
        job = wait(f"/jobs/{job['id']}")
        assert job["state"] == "succeeded", job
        status, page = call("GET", f"/console/reconstructions/{job['id']}")
        assert status == 200 and b"niivue" in page
        library = re.search(rb'src="(/static/vendor/niivue[^"]+)"', page)
        assert library, "the viewer page loads no niivue"
        status, script = call("GET", library.group(1).decode())
        from orbitct_app.console.assets import FETCHED

        assert status == 200 and hashlib.sha256(script).hexdigest() == FETCHED[0][3], "the viewer's library differs"
        print(
            f"console smoke test passed: signed in, scanned, reconstructed, viewer with {len(script)} bytes of niivue"
        )
    finally:
        serve.terminate()
        serve.wait(timeout=60)


if __name__ == "__main__":
    main()
