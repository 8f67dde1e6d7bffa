"""Write orbitct's scan file from a bluesky run's document stream (start, descriptors, events, stop).

A run recorded this way is calibrated and reconstructed by ``orbitct calibrate`` and ``orbitct reconstruct``
unchanged. What the run must carry:

- the start document, under ``orbitct`` (:func:`orbitct_metadata` makes it): the panel (rows, cols, pitches in
  mm), the orbit's name and parameters, and every recorded axis (``device.axis`` as orbitct names it) with its
  unit and the data keys of its read-back and of its commanded position (event-model forbids dots in keys);
- events of one stream (``primary`` unless told) with the frame (``image``, filled: a 2-D array, not a reference
  to an external resource), its ``image_key`` (0 projection, 1 flat, 2 dark), for projections its nominal view
  (``nominal_vector``, 12 numbers: source, detector centre, u and v pixel vectors in mm, as in the scan file), and
  the axes' keys named in the start document;
- on orbitct's twins, the view each projection was imaged at (``true_vector``, simulation truth; the start
  entry names its key, or None where there is none);
- the data keys of frame, image key and views may be renamed (``keys`` of :func:`orbitct_metadata`: an ophyd-async
  panel named ``panel`` reads ``panel-image``);
- the stop document: ``exit_status`` ``success`` ends the file ``complete``; anything else ends it ``aborted``
  with the stop's reason, keeping every frame written so far.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import event_model
import numpy as np

from orbitct.geometry import Panel
from orbitct.scanfile import ImageKey, ScanWriter

KEY = "orbitct"
FORMAT = "orbitct-bluesky/1"
#: the data keys a run's events carry, unless its ``orbitct`` entry renames them
DEFAULT_KEYS: dict[str, str | None] = {
    "image": "image",
    "image_key": "image_key",
    "nominal_vector": "nominal_vector",
    "true_vector": None,
}


def orbitct_metadata(
    panel: Panel,
    axes: Mapping[str, tuple[str, str, str]],
    *,
    orbit_name: str = "",
    orbit_params: Mapping[str, Any] | None = None,
    marker_diameter_mm: float | None = None,
    keys: Mapping[str, str | None] | None = None,
    frames: tuple[Sequence[int], Sequence[Sequence[float]]] | None = None,
) -> dict[str, Any]:
    """The start document's ``orbitct`` entry: ``axes`` maps each axis (``device.axis``) to its unit and the data
    keys of its read-back and commanded position, e.g. ``{"rotation_stage.R": ("deg", "stage_R", "stage_R_set")}``;
    ``keys`` renames the data keys of ``image``, ``image_key``, ``nominal_vector`` and ``true_vector`` (None:
    the run has none); ``frames``: every planned frame's image key and nominal view (NaN for darks and flats),
    which live calibration needs before the first frame."""
    unknown = sorted(set(keys or {}) - set(DEFAULT_KEYS))
    if unknown:
        raise ValueError(f"orbitct_metadata: no data key {', '.join(unknown)}; keys are {', '.join(DEFAULT_KEYS)}")
    return {
        "format": FORMAT,
        "panel": {
            "rows": panel.rows,
            "cols": panel.cols,
            "pitch_col_mm": panel.pitch_col,
            "pitch_row_mm": panel.pitch_row,
        },
        "orbit": {"name": orbit_name, "params": dict(orbit_params or {})},
        # a list, not a mapping: event-model forbids dots in a document's keys, and axes are named device.axis
        "axes": [{"name": name, "unit": u, "readback": rb, "commanded": cmd} for name, (u, rb, cmd) in axes.items()],
        "marker_diameter_mm": marker_diameter_mm,
        "keys": {**DEFAULT_KEYS, **dict(keys or {})},
        **({} if frames is None else {"frames": _frames_entry(*frames)}),
    }


def _frames_entry(image_key: Sequence[int], nominal_vectors: Sequence[Sequence[float]]) -> dict[str, Any]:
    """The planned frames as a start document holds them (JSON: NaN as None)."""
    vectors = np.asarray(nominal_vectors, dtype=float).reshape(-1, 12)
    keys = [int(k) for k in image_key]
    if len(keys) != len(vectors):
        raise ValueError(f"orbitct_metadata: {len(keys)} image keys but {len(vectors)} nominal views")
    return {
        "image_key": keys,
        "nominal_vectors": [[None if np.isnan(x) else float(x) for x in row] for row in vectors],
    }


def entry_panel(entry: Mapping[str, Any]) -> Panel:
    """The panel an ``orbitct`` start entry describes."""
    p = entry["panel"]
    return Panel(int(p["rows"]), int(p["cols"]), float(p["pitch_col_mm"]), float(p["pitch_row_mm"]))


def entry_keys(entry: Mapping[str, Any]) -> dict[str, str | None]:
    """The data keys of frame, image key and views an ``orbitct`` start entry names (the defaults where it names
    none, as entries written before keys were named)."""
    return {**DEFAULT_KEYS, **dict(entry.get("keys") or {})}


class ScanFileCallback(event_model.DocumentRouter):
    """A bluesky callback (``callback(name, doc)``) writing each run it sees to ``path`` as an orbitct scan file.

    ``stream``: the event stream holding the frames. A run without the ``orbitct`` start entry is refused with a
    ValueError naming what is missing, before anything is written.
    """

    def __init__(self, path: str | os.PathLike[str], *, stream: str = "primary", overwrite: bool = False) -> None:
        super().__init__()
        self.path = Path(path)
        self.stream = stream
        self.overwrite = overwrite
        self.writer: ScanWriter | None = None
        self._axes: dict[str, dict[str, str]] = {}
        self._t0 = 0.0
        self._descriptors: set[str] = set()
        self._keys: dict[str, str | None] = dict(DEFAULT_KEYS)

    def start(self, doc: Mapping[str, Any]) -> None:
        md = doc.get(KEY)
        if not isinstance(md, Mapping) or md.get("format") != FORMAT:
            raise ValueError(
                f"the run's start document has no {KEY!r} entry of format {FORMAT!r}: make it with "
                "orbitct_bluesky.orbitct_metadata(panel, axes, ...) and pass it as the run's metadata"
            )
        panel = entry_panel(md)
        self._axes = {str(a["name"]): dict(a) for a in md["axes"]}
        self._keys = entry_keys(md)
        self._t0 = float(doc["time"])
        self.writer = ScanWriter(
            self.path,
            panel,
            axes={name: spec["unit"] for name, spec in self._axes.items()},
            orbit_name=str(md["orbit"]["name"]),
            orbit_params=dict(md["orbit"]["params"]),
            config={"recorded_by": "bluesky", "run_uid": str(doc["uid"])},
            marker_diameter_mm=md.get("marker_diameter_mm"),
            true_geometry=self._keys["true_vector"] is not None,
            overwrite=self.overwrite,
        )
        started = datetime.fromtimestamp(self._t0, UTC).isoformat(timespec="seconds")
        planned = doc.get("num_points")
        self.writer.set_attrs(
            "acquisition",
            recorded_by="bluesky",
            run_uid=str(doc["uid"]),
            plan_name=str(doc.get("plan_name", "")),
            started_utc=started,
            **({"planned_frames": int(planned)} if isinstance(planned, int) else {}),
        )

    def descriptor(self, doc: Mapping[str, Any]) -> None:
        if doc.get("name") != self.stream:
            return
        keys = set(doc["data_keys"])
        needed = {str(self._keys["image"]), str(self._keys["image_key"])}
        needed |= {s[k] for s in self._axes.values() for k in ("readback", "commanded")}
        missing = sorted(needed - keys)
        if missing:
            raise ValueError(f"stream {self.stream!r} lacks the data keys {missing} that the run's orbitct entry names")
        self._descriptors.add(str(doc["uid"]))

    def event(self, doc: Mapping[str, Any]) -> None:  # type: ignore[override]
        if doc.get("descriptor") not in self._descriptors or self.writer is None:
            return
        data = doc["data"]
        keys = self._keys
        key = ImageKey(int(data[str(keys["image_key"])]))
        projection = key == ImageKey.PROJECTION
        vector = data.get(str(keys["nominal_vector"])) if projection else None
        truth = data.get(str(keys["true_vector"])) if projection and keys["true_vector"] is not None else None
        self.writer.append(
            np.asarray(data[str(keys["image"])]),
            key,
            float(doc["time"]) - self._t0,
            nominal_vector=None if vector is None else np.asarray(vector, dtype=float),
            true_vector=None if truth is None else np.asarray(truth, dtype=float),
            encoders={name: float(data[s["readback"]]) for name, s in self._axes.items()},
            commanded={name: float(data[s["commanded"]]) for name, s in self._axes.items()},
        )

    def stop(self, doc: Mapping[str, Any]) -> None:
        if self.writer is None:
            return
        ok = doc.get("exit_status") == "success"
        reason = "" if ok else str(doc.get("reason") or f"the run ended with exit status {doc.get('exit_status')}")
        self.writer.finish("complete" if ok else "aborted", reason)
        self.writer = None
