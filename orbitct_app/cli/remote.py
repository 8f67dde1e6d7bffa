"""``orbitct stop``, ``orbitct reset`` and ``orbitct reset-fault``: the safety actions of a running service.

``stop`` goes to the guard's own stop listener (``--stop-url``; by default the service's port + 1)
and falls back to ``POST /stop`` on the service; any valid token may stop. ``reset`` and
``reset-fault`` need an operator's token. The token comes from ``--token`` or ``ORBITCT_TOKEN``.
"""

from __future__ import annotations

import sys
from typing import Any
from urllib.parse import urlsplit, urlunsplit

import click
import httpx

from orbitct_app.cli.failure import fail
from orbitct_app.error_codes import CATALOGUE, code_for_http

TIMEOUT_S = 15.0


def _default_stop_url(url: str) -> str:
    parts = urlsplit(url)
    port = parts.port or (443 if parts.scheme == "https" else 80)
    return urlunsplit((parts.scheme, f"{parts.hostname}:{port + 1}", "/stop", "", ""))


def _connection(fn: Any) -> Any:
    fn = click.option(
        "--token",
        envvar="ORBITCT_TOKEN",
        required=True,
        help="Bearer token (or ORBITCT_TOKEN); `orbitct token create --role operator|viewer`.",
    )(fn)
    fn = click.option(
        "--url",
        envvar="ORBITCT_URL",
        default="http://127.0.0.1:8000",
        show_default=True,
        help="The service (or ORBITCT_URL).",
    )(fn)
    return fn


def _post(url: str, token: str, body: dict[str, Any] | None = None) -> httpx.Response:
    return httpx.post(url, json=body or {}, headers={"Authorization": f"Bearer {token}"}, timeout=TIMEOUT_S)


def _check(r: httpx.Response, ok: tuple[int, ...]) -> dict[str, Any]:
    try:
        body = r.json()
    except ValueError:
        body = {"message": r.text[:300]}
    if r.status_code not in ok:
        code = body.get("error") if body.get("error") in CATALOGUE else code_for_http(r.status_code)
        said = body.get("message") or body.get("detail") or body
        fail(f"the service answered {r.status_code}: {said}", code, "" if body.get("advice") else None)
    return dict(body)


@click.command()
@_connection
@click.option(
    "--stop-url",
    envvar="ORBITCT_STOP_URL",
    default=None,
    help="The guard's stop listener (default: the service's port + 1, /stop; or ORBITCT_STOP_URL).",
)
@click.option("--reason", default="", help="Why the bench is stopped (logged and kept with the latch).")
def stop(url: str, token: str, stop_url: str | None, reason: str) -> None:
    """Emergency stop: halt every axis, X-rays off, abort the scan; latched until an operator resets it.

    Exit status 0 when every device was read back halted, 3 when the service could not verify it
    (the reply names what), 2 when no stop could be delivered.
    """
    target = stop_url or _default_stop_url(url)
    try:
        r = _post(target, token, {"reason": reason})
    except httpx.HTTPError as exc:
        click.echo(f"stop listener {target} not reachable ({exc}); trying {url}/stop", err=True)
        try:
            r = _post(f"{url.rstrip('/')}/stop", token, {"reason": reason})
        except httpx.HTTPError as exc2:
            fail(
                f"no stop delivered: neither {target} nor {url} answered ({exc2})",
                "unavailable",
                "stop the bench by hand (its emergency stop button), then check the service",
                exit_status=2,
            )
    body = _check(r, (202,))
    click.echo(("HALTED" if body["halted"] else "NOT VERIFIED") + f" (latched; {body['message']})")
    for device in body.get("devices", []):
        what = device["verified"] if device["halted"] else device["problem"]
        click.echo(f"  {device['device']}: {'ok' if device['halted'] else 'NOT verified'} - {what}")
    for key in ("latch_problem", "note"):
        if body.get(key):
            click.echo(f"warning: {body[key]}", err=True)
    if not body["halted"]:
        sys.exit(3)


@click.command()
@_connection
@click.option("--note", default="", help="What was checked before resetting (logged with who and when).")
def reset(url: str, token: str, note: str) -> None:
    """Reset a latched emergency stop (operator): scans and moves are allowed again; nothing moves by itself."""
    try:
        r = _post(f"{url.rstrip('/')}/stop/reset", token, {"note": note})
    except httpx.HTTPError as exc:
        fail(f"the service at {url} did not answer ({exc})", "unavailable")
    body = _check(r, (200,))
    last = body.get("last_reset") or {}
    click.echo(f"emergency stop reset by {last.get('by')} at {last.get('utc')}")


@click.command("reset-fault")
@_connection
@click.argument("device", default="xray")
def reset_fault(url: str, token: str, device: str) -> None:
    """Reset the X-ray generator's latched fault (operator); refused, naming the cause, while it persists."""
    try:
        r = _post(f"{url.rstrip('/')}/devices/{device}/reset-fault", token)
    except httpx.HTTPError as exc:
        fail(f"the service at {url} did not answer ({exc})", "unavailable")
    body = _check(r, (200,))
    state = body["state"]
    click.echo(f"{device}: fault reset; state {state.get('state')}, fault {state.get('fault')}")
