"""MkDocs hook: the reference pages that are generated from the code (orbitct_app/reference_pages.py)."""

from __future__ import annotations

from typing import Any

from mkdocs.structure.files import File, Files


def on_files(files: Files, config: Any) -> Files:
    """Add the generated pages to the site."""
    from orbitct_app import reference_pages

    for path, function in reference_pages.PAGES.items():
        files.append(File.generated(config, path, content=getattr(reference_pages, function)()))
    return files
