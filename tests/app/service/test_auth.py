"""Tokens stored as hashes, the ``token create|list|revoke`` commands, 401 and 403 on every mutating endpoint."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from click.testing import CliRunner

from orbitct_app.cli.serve import token
from orbitct_app.service.core.auth import (
    PERMISSIONS,
    TokenRegistry,
    create_token,
    hash_token,
    read_token_file,
)
from orbitct_app.service.core.settings import load_settings

pytestmark = pytest.mark.system

# method, path, body, permission needed (None: any valid token)
MUTATING = [
    ("POST", "/stop", None, "stop"),
    ("POST", "/stop/reset", None, "reset"),
    ("POST", "/devices/xray/reset-fault", None, "motion"),
    ("POST", "/devices/hexapod/reference", None, "motion"),
    ("POST", "/devices/hexapod/move", {"targets": {"X": 0.0}}, "motion"),
    ("POST", "/devices/hexapod/stop", None, "motion"),
    ("POST", "/scans", {"orbit": "circular", "params": {"n_frames": 4}}, "scan"),
    ("POST", "/scans/nope/abort", None, "scan"),
    ("POST", "/scans/nope/pause", None, "scan"),
    ("POST", "/scans/nope/resume", None, "scan"),
    ("POST", "/calibrations", {"scan_id": "nope"}, "analysis"),
    ("POST", "/reconstructions", {"scan_id": "nope"}, "analysis"),
    ("POST", "/jobs/nope/cancel", None, "analysis"),
    ("POST", "/people", {"name": "someone-new", "roles": ["viewer"]}, "people"),
    ("DELETE", "/people/nobody", None, "people"),
]
READS = [
    "/stop",
    "/devices",
    "/orbits",
    "/scans",
    "/jobs",
    "/calibrations",
    "/reconstructions",
    "/scans/nope",
    "/jobs/nope",
]


def test_token_file_holds_only_hashes(tmp_path: Path) -> None:
    path = tmp_path / "tokens.json"
    tok = create_token(path, "analyst", "alice")
    text = path.read_text()
    assert tok not in text and hash_token(tok) in text
    assert path.stat().st_mode & 0o077 == 0
    [entry] = read_token_file(path)
    assert (entry.role, entry.name) == ("analyst", "alice")
    reg = TokenRegistry([], path)
    assert reg.authenticate(tok).role == "analyst"
    assert reg.authenticate(tok + "x") is None


def test_cli_token_create_prints_once_and_stores_hash(tmp_path: Path) -> None:
    result = CliRunner().invoke(token, ["create", "--role", "viewer", "--name", "bob", "--data-dir", str(tmp_path)])
    assert result.exit_code == 0, result.output
    printed = result.stdout.strip().splitlines()[0]
    stored = json.loads((tmp_path / "tokens.json").read_text())["tokens"]
    assert stored == [{"sha256": hash_token(printed), "roles": ["viewer"], "name": "bob"}]
    bad = CliRunner().invoke(token, ["create", "--role", "admin", "--data-dir", str(tmp_path)])
    assert bad.exit_code != 0


def test_cli_token_list_and_revoke(tmp_path: Path, shared_api) -> None:  # type: ignore[no-untyped-def]
    def cli(*args: str):  # type: ignore[no-untyped-def]
        return CliRunner().invoke(token, [*args, "--tokens-file", str(tokens_file)])

    tokens_file = shared_api.data_dir / "tokens.json"
    assert cli("create", "--role", "viewer", "--name", "carol").exit_code == 0
    tok = create_token(tokens_file, "viewer", "dave")
    assert shared_api.get("/scans", role=None, headers={"Authorization": f"Bearer {tok}"}).status_code == 200
    listed = cli("list")
    assert listed.exit_code == 0 and "carol" in listed.stdout and hash_token(tok)[:12] in listed.stdout
    assert tok not in listed.output
    assert "exists already" in cli("create", "--role", "viewer", "--name", "carol").output
    gone = cli("revoke", hash_token(tok)[:10])
    assert gone.exit_code == 0 and "revoked dave" in gone.stdout
    assert shared_api.get("/scans", role=None, headers={"Authorization": f"Bearer {tok}"}).status_code == 401
    missing = cli("revoke", "nobody")
    assert missing.exit_code == 1 and "no token named 'nobody'" in missing.output and "carol" in missing.output
    assert cli("revoke", "carol").exit_code == 0 and "carol" not in cli("list").stdout


def test_one_sign_in_carries_several_roles_and_old_files_still_read(tmp_path: Path, shared_api) -> None:  # type: ignore[no-untyped-def]
    """A technician who scans and calibrates needs one token, not two; a tokens file of one role per token (as
    written before) still signs its people in."""
    tokens_file = shared_api.data_dir / "tokens.json"
    made = CliRunner().invoke(
        token,
        ["create", "--role", "operator", "--role", "analyst", "--name", "tech", "--tokens-file", str(tokens_file)],
    )
    assert made.exit_code == 0 and "roles operator, analyst" in made.output, made.output
    tok = made.stdout.strip().splitlines()[0]
    as_tech = {"Authorization": f"Bearer {tok}"}
    try:
        who = shared_api.post("/session", role=None, json={"token": tok}).json()
    finally:
        shared_api.client.cookies.clear()  # the shared client stays signed out for the other tests
    assert who["roles"] == ["operator", "analyst"] and who["role"] == "operator, analyst"
    assert {"scan", "analysis", "reset"} <= set(who["permissions"])
    # one token passes the checks of both roles (a 4xx past the permission check is the route's own answer)
    for method, path, body in (("POST", "/scans", {"orbit": "nope"}), ("POST", "/calibrations", {"scan_id": "x"})):
        r = shared_api.request(method, path, role=None, json=body, headers=as_tech)
        assert r.status_code not in (401, 403), r.text
    listed = CliRunner().invoke(token, ["list", "--tokens-file", str(tokens_file)])
    assert "operator, analyst" in listed.stdout
    old = tmp_path / "old.json"
    old.write_text(json.dumps({"tokens": [{"sha256": hash_token("oct_old"), "role": "viewer", "name": "v"}]}))
    assert TokenRegistry([], old).authenticate("oct_old").roles == ("viewer",)


def test_no_default_token_outside_sim() -> None:
    with pytest.raises(ValueError, match="dev_token"):
        load_settings(None, sim=False, dev_token="oct_dev_token_for_tests_only")


def test_health_and_docs_need_no_token(shared_api) -> None:  # type: ignore[no-untyped-def]
    assert shared_api.get("/health", role=None).status_code == 200
    assert shared_api.get("/openapi.json", role=None).status_code == 200
    assert shared_api.get("/docs", role=None).status_code == 200


@pytest.mark.parametrize("path", READS)
def test_reads_need_a_token(shared_api, path: str) -> None:  # type: ignore[no-untyped-def]
    r = shared_api.get(path, role=None)
    assert r.status_code == 401 and r.json()["error"] == "unauthorized"
    assert r.headers["www-authenticate"] == "Bearer"
    r = shared_api.client.get(path, headers={"Authorization": "Bearer oct_not_a_token"})
    assert r.status_code == 401
    r = shared_api.client.get(path, headers={"Authorization": "Basic dXNlcjpwdw=="})
    assert r.status_code == 401
    assert shared_api.get(path, role="viewer").status_code in (200, 404)


@pytest.mark.parametrize(("method", "path", "body", "permission"), MUTATING)
def test_roles_on_every_mutating_endpoint(
    shared_api, method: str, path: str, body: dict | None, permission: str
) -> None:  # type: ignore[no-untyped-def]
    r = shared_api.request(method, path, role=None, json=body)
    assert r.status_code == 401, r.text
    for role in ("operator", "analyst", "viewer"):
        r = shared_api.request(method, path, role=role, json=body)
        if permission in PERMISSIONS[role]:
            assert r.status_code not in (401, 403), (role, r.text)
        else:
            assert r.status_code == 403, (role, r.text)
            needed = [k for k in ("operator", "analyst", "viewer") if permission in PERMISSIONS[k]]
            said = r.json()["message"]
            assert r.json()["error"] == "forbidden" and f"needs the {' or '.join(needed)} role" in said, said
            assert f"signed in as {role};" in said and permission not in said.split(";")[0], said
            assert r.json()["advice"].startswith("ask an operator to add that role"), said
