"""MkDocs hook: the performance page's results, from the benchmarks' own output files (benchmarks/results/*.json)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

RESULTS = Path(__file__).resolve().parents[2] / "benchmarks" / "results"
MARKER = "<!-- benchmark results -->"


def results_markdown(folder: Path = RESULTS) -> str:
    """One section per recorded benchmark: its command, when and where it ran, and what it printed."""
    sections = []
    for path in sorted(folder.glob("*.json")):
        r = json.loads(path.read_text(encoding="utf-8"))
        status = "" if r["exit_status"] == 0 else f" **It failed (exit status {r['exit_status']}).**"
        load = ", ".join(f"{x:g}" for x in r["load_before"]) or "unknown"
        sections.append(
            "\n".join(
                [
                    f"### {r['benchmark']}",
                    "",
                    f"`{r['command']}`, started {r['started_utc'].replace('T', ' ').replace('+00:00', ' UTC')}, "
                    f"{r['seconds']:g} s; {r['machine']}; load average before (1, 5, 15 min): {load}.{status}",
                    "",
                    "```text",
                    r["output"],
                    "```",
                    "",
                ]
            )
        )
    return "\n".join(sections) if sections else "No benchmark has been recorded yet: `python benchmarks/record.py`.\n"


def on_page_markdown(markdown: str, page: Any, config: Any, files: Any) -> str:
    """Put the recorded results where the performance page asks for them."""
    return markdown.replace(MARKER, results_markdown()) if MARKER in markdown else markdown
