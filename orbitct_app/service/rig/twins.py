"""The simulated bench of ``orbitct serve --sim``: the twins in a process of their own, as hardware would be.

The rig process and the guard reach them over loopback sockets exactly as they reach real
controllers, so the rig process can die and be restarted (and the guard can still stop the
devices meanwhile) without the simulated hardware going with it. The twins ignore the
service's signals and end when the web server does: at once when it shuts them down, a few seconds after
it died otherwise, so that the orphaned rig process halts them and closes its scan as it would on hardware.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing as mp
import os
import signal
import threading
import time
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

from acquire.rigs.links import DeviceLink
from devices.uri import parse_uri
from orbitct_app.service.core.children import Backoff, end_child

log = logging.getLogger("orbitct.service.twins")
_CTX = mp.get_context("spawn")
START_TIMEOUT_S = 120.0
#: how long the twins outlive a web server that died without shutting them down (seconds)
ORPHAN_GRACE_S = 5.0


def twins_main(config_path: str, ports: dict[str, int], conn: Connection, nice: int = 0) -> None:
    """Entry point of the twins process: start the rig's twins, report their links, serve until the pipe closes.

    It asks for the rig process's priority (``nice``): the simulated hardware must not starve behind the web
    server any more than real hardware would.
    """
    from acquire.config import load_config
    from acquire.rigs import sim_twins

    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(levelname)s twins: %(message)s")
    if nice < 0:
        with contextlib.suppress(OSError):
            os.setpriority(os.PRIO_PROCESS, 0, nice)
    for sig in (signal.SIGTERM, signal.SIGHUP, signal.SIGINT):
        signal.signal(sig, signal.SIG_IGN)  # the hardware outlives the software's shutdown; the pipe ends it
    try:
        config = load_config(config_path)
        context = sim_twins(config, ports)
        running = context.__enter__()
    except Exception as exc:  # noqa: BLE001 - reported to the web server, which stays up degraded
        with contextlib.suppress(OSError):
            conn.send(("failed", str(exc)))
        return
    try:
        conn.send(("ready", {k: (v.uri, v.options) for k, v in running.links.items()}))
        try:
            while True:
                message = conn.recv()
                if message == "shutdown":
                    break
                conn.send(("hazard", _hazard(running.twins, *message[1:])))
        except (EOFError, OSError):  # the web server died: hardware would still be there for the orphaned rig
            time.sleep(ORPHAN_GRACE_S)  # process and the guard to halt, read back and close the scan file
    finally:
        context.__exit__(None, None, None)


def _hazard(twins: dict[str, Any], kind: str, name: str, value: Any) -> str:
    """Set a fault or hazard on a running twin (``faults.*``, ``readout_s``, ``door``, ``fault``, ``fault_input``)."""
    if kind not in twins:
        return f"no twin {kind!r}"
    sim = twins[kind]
    twin = sim.twin
    if name.startswith("faults.") and hasattr(twin.faults, name[7:]):
        setattr(twin.faults, name[7:], value)
    elif name == "readout_s" and hasattr(twin, "readout_s"):
        twin.readout_s = float(value)
    elif name == "door" and hasattr(twin, "set_door"):
        sim.thread.call(twin.set_door, bool(value))
    elif name == "fault" and hasattr(twin, "raise_fault"):
        sim.thread.call(twin.raise_fault, int(value))
    elif name == "fault_input" and hasattr(twin, "set_fault_input"):
        sim.thread.call(twin.set_fault_input, bool(value))
    else:
        return f"twin {kind!r} has no hazard {name!r}"
    return "ok"


class SimBench:
    """Starts the twins process, hands out the links to its twins, and restarts it on the same ports if it dies."""

    def __init__(self, config_path: Path, nice: int = 0) -> None:
        self.config_path = Path(config_path)
        self.nice = nice
        self.state = "not started"
        self.links: dict[str, DeviceLink] = {}
        self._ports: dict[str, int] = {}
        self._process: Any = None
        self._conn: Any = None
        self._ready = threading.Event()
        self._closing = False
        self._backoff = Backoff()
        self._started_at = 0.0
        self._hazard_lock = threading.Lock()
        self._hazard_done = threading.Event()
        self._hazard_reply = ""

    def start(self) -> dict[str, DeviceLink]:
        """Start the twins and wait until they serve; their links (empty if they could not start)."""
        parent, child = _CTX.Pipe()
        self._ready.clear()
        self.state = "starting"
        self._process = _CTX.Process(
            target=twins_main,
            name="orbitct-twins",
            daemon=True,
            args=(str(self.config_path), self._ports, child, self.nice),
        )
        self._process.start()
        child.close()
        self._conn = parent
        self._started_at = time.monotonic()
        threading.Thread(target=self._read, args=(parent,), name="orbitct-twins-events", daemon=True).start()
        if not self._ready.wait(START_TIMEOUT_S):
            self.state = f"failed: the simulated bench did not start within {START_TIMEOUT_S:g} s"
        return self.links if self.state == "running" else {}

    def _read(self, conn: Any) -> None:
        while True:
            try:
                message = conn.recv()
            except (EOFError, OSError):
                break
            if message[0] == "ready":
                self.links = {k: DeviceLink(uri, opts) for k, (uri, opts) in message[1].items()}
                self._ports = {k: int(parse_uri(v.uri).port or 0) for k, v in self.links.items()}
                self.state = "running"
                self._ready.set()
            elif message[0] == "failed":
                self.state = f"failed: {message[1]}"
                self._ready.set()
            elif message[0] == "hazard":
                self._hazard_reply = str(message[1])
                self._hazard_done.set()
        self._ready.set()
        if self._closing or not self._ports:
            return
        delay = self._backoff.delay(time.monotonic() - self._started_at)
        self.state = f"restarting: the simulated bench ended (restart {self._backoff.restarts} in {delay:g} s)"
        log.error("%s", self.state)
        time.sleep(delay)
        if not self._closing:
            self.start()

    def hazard(self, kind: str, name: str, value: Any) -> None:
        """Set a fault or hazard on one running twin (tests and demonstrations): ``faults.garble_next``,
        ``faults.latency_s``, ``readout_s`` (slow panel), ``door`` (interlock), ``fault`` (generator fault code),
        ``fault_input`` (a generator fault input that stays asserted)."""
        with self._hazard_lock:
            self._hazard_done.clear()
            self._conn.send(("hazard", kind, name, value))
            if not self._hazard_done.wait(10.0) or self._hazard_reply != "ok":
                raise ValueError(self._hazard_reply or "the simulated bench did not answer")

    def close(self) -> None:
        """Stop the twins (after the rig has let go of them)."""
        self._closing = True
        end_child(self._process, self._conn, 15.0)
        self.state = "closed"
