"""Third-party files the console serves that are too large to keep in the repository, fetched once at set-up.

``python -m orbitct_app.console.assets`` (run by ``make``) downloads each pinned npm package, takes the one file
the console needs, checks its SHA-256 and puts it under ``static/vendor/``; a machine without access to the npm
registry can be given the file by copying it there. Without it the viewer shows PNG slices and says why.
"""

from __future__ import annotations

import hashlib
import io
import sys
import tarfile
import urllib.request
from pathlib import Path

VENDOR = Path(__file__).resolve().parent / "static" / "vendor"
# (npm tarball, member, where it goes, its SHA-256)
FETCHED = [
    (
        "https://registry.npmjs.org/@niivue/niivue/-/niivue-0.69.0.tgz",
        "package/dist/niivue.umd.js",
        VENDOR / "niivue-0.69.0" / "niivue.umd.js",
        "47b896b77ec4a5be3ef1949c33ad393b6f45629921f326c279000bcf51bdb4af",
    )
]


def fetch(timeout_s: float = 120.0) -> list[Path]:
    """Download what is missing or different; RuntimeError naming the file if a download fails or does not match."""
    done = []
    for url, member, target, sha in FETCHED:
        if target.is_file() and hashlib.sha256(target.read_bytes()).hexdigest() == sha:
            continue
        try:
            with urllib.request.urlopen(url, timeout=timeout_s) as r:
                data = r.read()
            with tarfile.open(fileobj=io.BytesIO(data), mode="r:gz") as tar:
                extracted = tar.extractfile(member)
                content = extracted.read() if extracted is not None else b""
        except (OSError, tarfile.TarError) as exc:
            raise RuntimeError(
                f"{target.name}: cannot fetch {url} ({exc}); copy the file to {target} by hand"
            ) from None
        if hashlib.sha256(content).hexdigest() != sha:
            raise RuntimeError(f"{target.name} from {url} does not have the pinned SHA-256 {sha}; not installed")
        target.parent.mkdir(parents=True, exist_ok=True)
        partial = target.with_suffix(".part")
        partial.write_bytes(content)
        partial.replace(target)
        done.append(target)
    return done


if __name__ == "__main__":
    try:
        got = fetch()
    except RuntimeError as exc:
        sys.exit(f"console assets: {exc}")
    print("console assets: " + (", ".join(p.name for p in got) + " installed" if got else "up to date"))
