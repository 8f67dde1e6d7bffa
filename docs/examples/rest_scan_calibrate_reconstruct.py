"""Scan, calibrate and reconstruct over orbitct's REST API: what a CI job or a lab script does.

Run it against a service (``orbitct serve --config config/bench.yaml --sim`` for the twins) with
``ORBITCT_URL`` and ``ORBITCT_TOKEN`` set (a token that may scan and calibrate). It exits 0 when the calibration
passed its quality check and the volume was made, 1 otherwise, and prints what it did.
"""

from __future__ import annotations

import os
import sys
import time

import httpx

ENDED = {"complete", "aborted", "failed", "interrupted", "succeeded", "cancelled"}


def wait(client: httpx.Client, path: str, timeout_s: float = 600.0) -> dict:
    """Poll a scan or job until it has ended; its last state."""
    t0 = time.monotonic()
    while True:
        state = client.get(path).raise_for_status().json()
        if state["state"] in ENDED:
            return state
        if time.monotonic() - t0 > timeout_s:
            sys.exit(f"{path} did not end within {timeout_s:.0f} s (state {state['state']})")
        time.sleep(1.0)


def main() -> int:
    url = os.environ.get("ORBITCT_URL", "http://127.0.0.1:8000")
    token = os.environ["ORBITCT_TOKEN"]
    with httpx.Client(base_url=url, headers={"Authorization": f"Bearer {token}"}, timeout=60) as client:
        # A scan: the pre-flight runs first, and nothing moves when a frame is infeasible (422 says which).
        scan = client.post("/scans", json={"name": "ci", "orbit": "sawtooth", "frames": 60}).raise_for_status().json()
        scan = wait(client, f"/scans/{scan['id']}")
        print(f"scan {scan['id']}: {scan['state']}, {scan['frames_done']} frames")
        if scan["state"] != "complete":
            print(f"the scan ended early: {scan['reason']}")
            return 1

        # Calibration from the BBs: the job succeeds when a geometry was stored; its quality verdict says
        # whether to trust it.
        job = client.post("/calibrations", json={"scan_id": scan["id"]}).raise_for_status().json()
        job = wait(client, f"/jobs/{job['id']}")
        quality = (job.get("result") or {}).get("quality") or {}
        print(f"calibration {job['id']}: {job['state']}, quality passed: {quality.get('passed')}")
        if job["state"] != "succeeded" or not quality.get("passed"):
            print("calibration not usable:", job.get("reason") or "; ".join(quality.get("reasons", [])))
            return 1

        # FDK with the calibrated geometry on a small grid, then one axial slice as PNG.
        request = {"scan_id": scan["id"], "algorithm": "fdk", "geometry": "calibrated", "shape": [48, 64, 64]}
        job = client.post("/reconstructions", json=request).raise_for_status().json()
        job = wait(client, f"/jobs/{job['id']}")
        print(f"reconstruction {job['id']}: {job['state']}")
        if job["state"] != "succeeded":
            print("reconstruction failed:", job.get("reason"))
            return 1
        png = client.get(f"/reconstructions/{job['id']}/slices/axial").raise_for_status().content
        with open("axial.png", "wb") as out:
            out.write(png)
        print(f"axial slice: axial.png ({len(png)} bytes)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
