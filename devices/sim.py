"""``sim://`` URIs: start the twin of a device kind and hand the driver a loopback endpoint.

Drivers never see ``sim://``: :func:`start_twin` starts (or reuses) the twin that a
``sim://<world>?<options>`` URI names and returns it with its real endpoint
(``tcp://127.0.0.1:<port>``, ``modbus://127.0.0.1:<port>``); the options the twin takes are
split from those the driver takes. Twins of one world share its simulated physics (the
motion twins write the true pose, the X-ray twin the exposures, the panel images them).

Motion controllers stay powered between connections, as real ones do: one hexapod and one
rotation-stage twin per world, until :func:`stop_twins` (or until a connection asks for other
twin options, which restarts it). Panels, generators and C-arms get a twin per connection,
stopped when their driver closes.
"""

from __future__ import annotations

import threading
import weakref
from dataclasses import dataclass
from typing import Any

from devices.errors import UriError
from devices.twins.runtime import TwinThread
from devices.twins.world import get_world
from devices.uri import option_value, parse_uri

_PANEL = {"rows", "cols", "pitch_mm", "sad_mm", "sdd_mm", "phantom", "seed", "detector_model", "beam", "readout_s"}
_MOTION = {"time_scale", "imperfect", "seed", "velocity", "stack_order"}
TWIN_OPTIONS: dict[str, set[str]] = {  # every twin also takes ``port`` (where it listens; 0 = a free port)
    "hexapod": _MOTION | {"port"},
    "rotation_stage": _MOTION | {"port"},
    "xray": {"prep_s", "time_scale", "port"},
    "detector": _PANEL | {"port"},
    "carm": _PANEL
    | {"sag_deg", "drift_mm", "eta_deg", "primary_offset_deg", "noise_mm", "time_scale", "limits", "port"},
}
SHARED_KINDS = ("hexapod", "rotation_stage")
DEFAULT_WORLDS = {"carm": "carm"}


@dataclass
class SimTwin:
    """A running twin: its kind, world and thread (``thread.twin`` is the twin object)."""

    kind: str
    world: str
    thread: TwinThread
    options: dict[str, Any]

    @property
    def twin(self) -> Any:
        """The twin object: faults, hazards, inspection."""
        return self.thread.twin

    @property
    def endpoint(self) -> str:
        """Where the driver connects (a loopback URI)."""
        return self.thread.uri

    def stop(self) -> None:
        """Stop the twin (idempotent)."""
        self.thread.stop()


_SHARED: dict[tuple[str, str], SimTwin] = {}
_LOCK = threading.Lock()
_OF_DEVICE: weakref.WeakKeyDictionary[Any, SimTwin] = weakref.WeakKeyDictionary()


def _make(kind: str, world: str, options: dict[str, Any]) -> TwinThread:
    options = dict(options)
    port = int(options.pop("port", 0))
    if kind in SHARED_KINDS:
        from devices.twins.gcs import start_twin

        return start_twin(kind, port=port, world=world, **options)
    if kind == "xray":
        from devices.twins.xray import XrayTwin

        return TwinThread(XrayTwin(get_world(world), **options), port=port)
    if kind == "detector":
        from devices.twins.detector import DetectorTwin

        return TwinThread(DetectorTwin(get_world(world), **options), port=port)
    from devices.twins.carm import CArmTwin

    return TwinThread(CArmTwin(get_world(world), **options), port=port)


def start_twin(
    kind: str, uri: str = "sim://bench", options: dict[str, Any] | None = None
) -> tuple[SimTwin, dict[str, Any]]:
    """The twin a ``sim://`` URI names (started now, or the world's running motion twin) and the driver's options.

    ``options`` holds keyword options for both; URI query values come as text and are read as numbers
    or booleans where they look like one. Unknown twin options are left to the driver, which names them.
    """
    kind = kind.replace("-", "_").lower()
    if kind not in TWIN_OPTIONS:
        raise UriError(f"sim:// has no twin of kind {kind!r}; kinds are {', '.join(sorted(TWIN_OPTIONS))}")
    ep = parse_uri(uri)
    if ep.scheme != "sim":
        raise UriError(f"{kind}: expected a sim:// URI, got {uri!r}")
    world = ep.host or DEFAULT_WORLDS.get(kind, "bench")
    merged = {**{k: option_value(v) for k, v in ep.params.items()}, **dict(options or {})}
    twin_opts = {k: v for k, v in merged.items() if k in TWIN_OPTIONS[kind]}
    driver_opts = {k: v for k, v in merged.items() if k not in TWIN_OPTIONS[kind]}
    stack_order = twin_opts.pop("stack_order", None)
    if stack_order is not None:
        w = get_world(world)
        with w.lock:
            w.stack_order = str(stack_order)
    if kind in SHARED_KINDS:
        with _LOCK:
            running = _SHARED.get((kind, world))
            if running is not None and running.thread.alive and running.options != twin_opts:
                running.stop()  # asked for other physics (time scale, imperfections): power-cycle the twin
            if running is None or not running.thread.alive or running.options != twin_opts:
                running = _SHARED[(kind, world)] = SimTwin(kind, world, _make(kind, world, twin_opts), twin_opts)
        return running, driver_opts
    return SimTwin(kind, world, _make(kind, world, twin_opts), twin_opts), driver_opts


def attach(device: Any, twin: SimTwin) -> None:
    """Remember ``device``'s twin (:func:`twin_of`); a twin of its own stops when the device closes."""
    _OF_DEVICE[device] = twin
    if twin.kind not in SHARED_KINDS:
        device.on_close(twin.stop)


def twin_of(device: Any) -> Any:
    """The twin object behind a device opened on a ``sim://`` URI (faults, hazards, inspection)."""
    try:
        return _OF_DEVICE[device].twin
    except KeyError:
        raise UriError(f"{getattr(device, 'name', device)!r} was not opened on a sim:// URI; it has no twin") from None


def stop_twins() -> None:
    """Stop every shared motion twin (the next ``sim://`` connection starts fresh ones)."""
    with _LOCK:
        running = list(_SHARED.values())
        _SHARED.clear()
    for twin in running:
        twin.stop()
