"""The third-party files the console serves are the pinned ones, each with its licence beside it."""

from __future__ import annotations

import hashlib
import re
from pathlib import Path

from orbitct_app.console.pages import STATIC

VENDOR = STATIC / "vendor"


def test_vendored_files_match_their_pinned_hashes_and_carry_their_licences() -> None:
    table = (VENDOR / "NOTICE.md").read_text(encoding="utf-8")
    pinned = re.findall(r"^\| `([^`]+)` \|.*\| `([0-9a-f]{64})` \|$", table, flags=re.M)
    assert len(pinned) == 4
    for name, digest in pinned:
        path = VENDOR / name
        assert hashlib.sha256(path.read_bytes()).hexdigest() == digest, f"{name} differs from the pinned file"
        assert (path.parent / "LICENSE").is_file(), f"{path.parent.name} has no licence file"
    served = {str(p.relative_to(VENDOR)) for p in VENDOR.rglob("*.js")} | {
        str(p.relative_to(VENDOR)) for p in VENDOR.rglob("*.css")
    }
    assert served == {name for name, _ in pinned}, "every script and style sheet under vendor/ is pinned"


def test_the_console_pages_load_only_the_pinned_library_versions() -> None:
    templates = Path(STATIC).parent / "templates"
    referenced = set(
        re.findall(r"vendor/([\w.-]+/[\w.-]+\.(?:js|css))", "".join(p.read_text() for p in templates.glob("*.html")))
    )
    assert referenced == {"niivue-0.69.0/niivue.umd.js"}
    for ref in referenced:
        assert (VENDOR / ref).is_file(), ref


def test_the_fetch_installs_only_the_pinned_file(tmp_path: Path, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    import io
    import tarfile

    import pytest

    from orbitct_app.console import assets

    body = b"console library"
    tgz = tmp_path / "pkg.tgz"
    with tarfile.open(tgz, "w:gz") as tar:
        info = tarfile.TarInfo("package/dist/lib.js")
        info.size = len(body)
        tar.addfile(info, io.BytesIO(body))
    target = tmp_path / "vendor" / "lib.js"
    monkeypatch.setattr(assets, "FETCHED", [(tgz.as_uri(), "package/dist/lib.js", target, "0" * 64)])
    with pytest.raises(RuntimeError, match="does not have the pinned SHA-256"):
        assets.fetch()
    assert not target.exists()
    monkeypatch.setattr(
        assets, "FETCHED", [(tgz.as_uri(), "package/dist/lib.js", target, hashlib.sha256(body).hexdigest())]
    )
    assert assets.fetch() == [target] and target.read_bytes() == body
    assert assets.fetch() == []  # already there
