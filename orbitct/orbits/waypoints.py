"""Reading ``rotation_deg, tilt_deg`` waypoint lists from CSV or YAML files."""

from __future__ import annotations

import csv
from pathlib import Path

import yaml

from orbitct.orbits.errors import OrbitError


def _pair(row: object, where: str) -> tuple[float, float]:
    try:
        if isinstance(row, dict):
            return float(row["rotation_deg"]), float(row["tilt_deg"])
        if isinstance(row, (list, tuple)) and len(row) == 2:
            return float(row[0]), float(row[1])
    except (KeyError, TypeError, ValueError):
        pass
    raise OrbitError(f"{where}: expected rotation_deg and tilt_deg numbers, got {row!r}")


def read_waypoints(path: str | Path) -> list[tuple[float, float]]:
    """Waypoints ``[(rotation_deg, tilt_deg), ...]`` from a CSV (header ``rotation_deg,tilt_deg``) or YAML file.

    YAML may be a list of ``{rotation_deg, tilt_deg}`` mappings or ``[rotation, tilt]`` pairs,
    optionally under a top-level ``waypoints`` key.
    """
    p = Path(path)
    if not p.is_file():
        raise OrbitError(f"waypoints file {p} does not exist")
    text = p.read_text()
    if p.suffix.lower() in (".yaml", ".yml", ".json"):
        try:
            data = yaml.safe_load(text)
        except yaml.YAMLError as exc:
            raise OrbitError(f"{p}: not valid YAML ({exc})") from None
        if isinstance(data, dict):
            data = data.get("waypoints")
        if not isinstance(data, list):
            raise OrbitError(f"{p}: expected a list of waypoints (or a 'waypoints' key holding one)")
        pts = [_pair(r, f"{p} item {i}") for i, r in enumerate(data)]
    else:
        rows = [r for r in csv.reader(text.splitlines()) if r and not r[0].lstrip().startswith("#")]
        if not rows:
            raise OrbitError(f"{p}: no waypoints")
        header = [c.strip() for c in rows[0]]
        if header[:2] == ["rotation_deg", "tilt_deg"]:
            rows = rows[1:]
        elif any(c.isalpha() for c in "".join(header)):
            raise OrbitError(f"{p}: CSV header must be 'rotation_deg,tilt_deg', got {','.join(header)!r}")
        pts = [_pair([c.strip() for c in r][:2] if len(r) >= 2 else r, f"{p} line {i + 1}") for i, r in enumerate(rows)]
    if len(pts) < 2:
        raise OrbitError(f"{p}: need at least 2 waypoints, got {len(pts)}")
    return pts
