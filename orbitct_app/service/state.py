"""Everything one running service owns: settings, store, event bus, tokens, the emergency stop (latch and guard
process), the rig process (and the simulated bench's twins with ``sim``), the job queue and the BB plans."""

from __future__ import annotations

import logging
import multiprocessing as mp
import secrets
import time
from pathlib import Path
from typing import Any

from orbitct_app.service.core.auth import TOKEN_PREFIX, TokenRegistry
from orbitct_app.service.core.datadir import DataDirLock
from orbitct_app.service.core.db import Store
from orbitct_app.service.core.events import EventBus
from orbitct_app.service.core.files import summarize_scan
from orbitct_app.service.core.sessions import SessionStore
from orbitct_app.service.core.settings import ServiceSettings
from orbitct_app.service.jobs.bbplans import PlanQueue
from orbitct_app.service.jobs.manager import JobManager
from orbitct_app.service.rig import SERVICE_STOPPED
from orbitct_app.service.rig.client import RigClient
from orbitct_app.service.rig.twins import SimBench
from orbitct_app.service.safety.client import GuardClient
from orbitct_app.service.safety.estop import EmergencyStop
from orbitct_app.service.safety.latch import SharedFlag, StopLatch

log = logging.getLogger("orbitct.service")
RESTART_REASON = "interrupted: the service stopped while it was running"


class Service:
    """Everything one running service owns; it holds its data directory (:class:`DataDirBusy` if another does)."""

    def __init__(self, settings: ServiceSettings) -> None:
        self.settings = settings
        settings.data_dir.mkdir(parents=True, exist_ok=True)
        self.data_lock = DataDirLock(settings.data_dir)
        self.data_lock.acquire(port=settings.port)  # before the database: a second service touches nothing
        self.dev_token: str | None = None
        self.stop_reason = f"{SERVICE_STOPPED} (shut down)"  # why a running scan is aborted when the service stops
        if settings.sim:
            self.dev_token = settings.dev_token or TOKEN_PREFIX + "dev_" + secrets.token_urlsafe(24)
        self.tokens = TokenRegistry(settings.tokens, settings.tokens_path, self.dev_token)
        self.sessions = SessionStore(self.tokens)
        self.store = Store(settings.db_path)
        self.bus = EventBus(self.store)
        self.latch = StopLatch(settings.data_dir, SharedFlag(mp.get_context("spawn")))
        self.sim_bench = SimBench(settings.bench_config, nice=settings.bench_nice) if settings.sim else None
        self.rig = RigClient(
            settings.bench_config,
            sim=settings.sim,
            store=self.store,
            bus=self.bus,
            data_dir=settings.data_dir,
            status_interval_s=settings.status_interval_s,
            nice=settings.bench_nice,
            latch_flag=self.latch.flag,
        )
        self.guard = GuardClient(
            settings, self.latch.flag, self.dev_token, on_stop=lambda reply: self.estop.published(reply)
        )
        self.estop = EmergencyStop(self.latch, self.guard, self.rig, self.bus)
        self.jobs = JobManager(
            self.store,
            self.bus,
            settings.data_dir,
            workers=settings.job_workers,
            cancel_grace_s=settings.cancel_grace_s,
            scan_busy=lambda s: self.rig.busy == s,
            scheduler=settings.dask_scheduler,
        )
        self.plans = PlanQueue(settings.data_dir / "plans")

    @property
    def reserve_mb(self) -> float:
        """Free space the bench configuration keeps on the data's disk (``storage.reserve_mb``)."""
        if not hasattr(self, "_reserve_mb"):
            from acquire.config import StorageConfig, load_config

            try:
                self._reserve_mb = float(load_config(self.settings.bench_config).storage.reserve_mb)
            except Exception:  # noqa: BLE001 - the rig process reports a bad configuration
                self._reserve_mb = float(StorageConfig().reserve_mb)
        return self._reserve_mb

    def disk(self) -> tuple[str, int]:
        """``(state, free bytes)`` of the data directory's disk: ``ok``, ``low`` (below the reserve) or ``full``."""
        from orbitct.diskspace import MB, free_bytes

        free = free_bytes(self.settings.data_dir)
        if free < 4 * MB:
            return "full", free
        return ("low" if free < self.reserve_mb * MB else "ok"), free

    def recover(self) -> tuple[list[str], list[str]]:
        """Mark scans and jobs a previous process left running as interrupted (or, when the scan file says the scan had
        ended on its own, as the file says); repair their scan files."""
        scan_ids, job_ids = self.store.mark_interrupted(RESTART_REASON)
        from acquire.repair import INTERRUPTED

        for scan_id in scan_ids:
            row = self.store.get_scan(scan_id)
            path = self.settings.data_dir / row["file"] if row else None
            summary: dict[str, object] = {}
            if path is not None and path.exists():
                summary = self._repair(path)
            fields: dict[str, object] = {"summary": summary}
            if isinstance(summary.get("n_frames"), int):
                fields["frames_done"] = summary["n_frames"]  # the record follows the file
            ended = str(summary.get("status_reason") or "")
            if summary.get("status") == "complete" or (
                summary.get("status") == "aborted" and ended != INTERRUPTED and not ended.startswith(SERVICE_STOPPED)
            ):
                # the scan had ended on its own, but its record could not be written before the service stopped
                # (a full disk, a read-only data directory): the record follows the file, with its true reason
                fields.update(state=summary["status"], reason=ended)
            self.store.update_scan(scan_id, **fields)
            self.bus.publish(
                f"scan:{scan_id}",
                "end",
                {"state": fields.get("state", "interrupted"), "reason": fields.get("reason", RESTART_REASON)},
            )
        for job_id in job_ids:
            self.bus.publish(f"job:{job_id}", "end", {"state": "interrupted", "reason": RESTART_REASON})
        if scan_ids or job_ids:
            log.warning("marked interrupted after restart: scans %s, jobs %s", scan_ids, job_ids)
        return scan_ids, job_ids

    @staticmethod
    def _repair(path: Path, wait_s: float = 15.0) -> dict[str, object]:
        """Mark a scan file left 'acquiring' as aborted (waiting while a dying bench process still holds it)."""
        from acquire.repair import repair_scan

        t0 = time.monotonic()
        while True:
            try:
                repair_scan(path)
                break
            except Exception as exc:  # noqa: BLE001 - keep what is there, say why it could not be repaired
                if time.monotonic() - t0 > wait_s:
                    log.error("could not repair %s: %s", path.name, exc)
                    break
                time.sleep(0.2)
        return summarize_scan(path)

    def _device_links(self) -> dict[str, Any] | None:
        """Where the devices are: the simulated bench's twins (started now), or the configuration's URIs."""
        from acquire.config import load_config
        from acquire.errors import ConfigError
        from acquire.rigs import rig_links

        if self.sim_bench is not None:
            links = self.sim_bench.start()
            if not links:
                log.error("simulated bench: %s", self.sim_bench.state)
            return links
        try:
            return rig_links(load_config(self.settings.bench_config), sim=False)
        except ConfigError as exc:  # the rig process reports it too; the service stays up, degraded
            log.error("%s", exc)
            return None

    def start(self) -> None:
        """Recover, start the simulated bench (sim), the guard and the rig process, then the job workers."""
        self.recover()
        if not self.settings.sim and len(self.tokens) == 0:
            log.warning(
                "no tokens configured: every request will get 401; create one with "
                "`orbitct token create --role operator --data-dir %s`",
                self.settings.data_dir,
            )
        if self.latch.latched:
            log.warning("%s", self.latch.refusal("scans, moves and referencing"))
        disk, free = self.disk()
        if disk != "ok":
            from orbitct.diskspace import format_bytes

            log.warning(
                "the data directory's disk is %s: %s free in %s, the bench keeps %s free "
                "(storage.reserve_mb); scans are refused until there is room",
                disk,
                format_bytes(free),
                self.settings.data_dir,
                format_bytes(self.reserve_mb * 2**20),
            )
        links = self._device_links()
        if links:
            self.guard.start(links)
            if self.guard.url is not None:
                log.warning("emergency stop listener (a process of its own): POST %s/stop", self.guard.url)
        else:
            self.guard.state = "failed: no device links (see the rig's connection state)"
        if self.sim_bench is not None and not links:
            self.rig.connection_state = f"failed: simulated bench: {self.sim_bench.state}"
        else:
            self.rig.start(links)
        self.jobs.start()
        self.plans.start()
        if self.dev_token is not None:
            log.warning("--sim development token (all roles): %s", self.dev_token)

    def close(self) -> None:
        """Stop plans, jobs and the rig (a running scan is aborted with :attr:`stop_reason`), flush events, close the
        store."""
        self.plans.close()
        self.jobs.shutdown()
        self.rig.close(self.stop_reason)
        self.guard.close()
        if self.sim_bench is not None:
            self.sim_bench.close()
        self.bus.close()
        self.store.close()
        self.data_lock.release()
