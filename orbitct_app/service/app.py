"""The FastAPI application: ``create_app(settings)`` wires store, events, bench, jobs and routers."""

from __future__ import annotations

import logging
import secrets
import time
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path

from fastapi import FastAPI

from orbitct import __version__
from orbitct_app.service.auth import TOKEN_PREFIX, TokenRegistry
from orbitct_app.service.bench import BenchController, scan_summary
from orbitct_app.service.db import Store
from orbitct_app.service.errors import ContentLengthLimit, install_error_handlers
from orbitct_app.service.events import EventBus
from orbitct_app.service.jobs import JobManager
from orbitct_app.service.routers import calibrations, devices, health, jobs, orbits, reconstructions, scans, stop
from orbitct_app.service.settings import ServiceSettings

log = logging.getLogger("orbitct_app.service")
RESTART_REASON = "interrupted: the service stopped while it was running"

TAGS = [
    {"name": "stop", "description": "Emergency stop: every axis halted, X-rays off. Any valid token."},
    {"name": "devices", "description": "Bench devices: state, referencing, maintenance moves (operator)."},
    {"name": "orbits", "description": "Orbit kinds, parameter schemas, validation and previews."},
    {"name": "scans", "description": "Acquisitions on the bench, one at a time (operator starts and aborts)."},
    {"name": "calibrations", "description": "Geometric calibration from BBs (analyst)."},
    {"name": "reconstructions", "description": "FDK and PWLS reconstruction (analyst)."},
    {"name": "jobs", "description": "State, progress, log and cancellation of calibration and reconstruction jobs."},
    {"name": "health", "description": "Liveness, no token needed."},
]


class Service:
    """Everything one running service owns."""

    def __init__(self, settings: ServiceSettings) -> None:
        self.settings = settings
        settings.data_dir.mkdir(parents=True, exist_ok=True)
        self.dev_token: str | None = None
        if settings.sim:
            self.dev_token = settings.dev_token or TOKEN_PREFIX + "dev_" + secrets.token_urlsafe(24)
        self.tokens = TokenRegistry(settings.tokens, settings.tokens_path, self.dev_token)
        self.store = Store(settings.db_path)
        self.bus = EventBus(self.store)
        self.bench = BenchController(settings.bench_config, sim=settings.sim, store=self.store, bus=self.bus,
                                     data_dir=settings.data_dir, status_interval_s=settings.status_interval_s,
                                     nice=settings.bench_nice)
        self.jobs = JobManager(self.store, self.bus, settings.data_dir, workers=settings.job_workers,
                               cancel_grace_s=settings.cancel_grace_s, scan_busy=lambda s: self.bench.busy == s)

    def recover(self) -> tuple[list[str], list[str]]:
        """Mark scans and jobs a previous process left running as interrupted; repair their scan files."""
        scan_ids, job_ids = self.store.mark_interrupted(RESTART_REASON)
        for scan_id in scan_ids:
            row = self.store.get_scan(scan_id)
            path = self.settings.data_dir / row["file"] if row else None
            summary: dict[str, object] = {}
            if path is not None and path.exists():
                summary = self._repair(path)
            self.store.update_scan(scan_id, summary=summary)
            self.bus.publish(f"scan:{scan_id}", "end", {"state": "interrupted", "reason": RESTART_REASON})
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
        return scan_summary(path)

    def start(self) -> None:
        """Recover, connect the bench, start the job workers."""
        self.recover()
        if not self.settings.sim and len(self.tokens) == 0:
            log.warning("no tokens configured: every request will get 401; create one with "
                        "`orbitct token create --role operator --data-dir %s`", self.settings.data_dir)
        self.bench.start()
        self.jobs.start()
        if self.dev_token is not None:
            log.warning("--sim development token (all roles): %s", self.dev_token)

    def close(self) -> None:
        """Stop jobs and the bench, flush events, close the store."""
        self.jobs.shutdown()
        self.bench.close()
        self.bus.close()
        self.store.close()


def create_app(settings: ServiceSettings, *, service: Service | None = None) -> FastAPI:
    """The orbitct REST application; its lifespan connects the devices (twins with ``sim``) and starts the workers."""
    svc = service or Service(settings)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        import anyio

        await anyio.to_thread.run_sync(svc.start)
        try:
            yield
        finally:
            await anyio.to_thread.run_sync(svc.close)

    app = FastAPI(
        title="orbitct",
        version=__version__,
        summary="Non-circular cone-beam CT on a bench: scans, BB calibration and reconstruction over HTTP.",
        description=(
            "Every endpoint but `/health` and the API docs needs `Authorization: Bearer <token>` "
            "(tokens from `orbitct token create --role operator|analyst|viewer`). Errors are JSON "
            "`{error, message, details: [{field, reason}]}`. Progress streams are server-sent events."
        ),
        openapi_tags=TAGS,
        lifespan=lifespan,
    )
    app.state.service = svc
    install_error_handlers(app)
    app.add_middleware(ContentLengthLimit, max_bytes=settings.max_body_bytes)
    for module in (health, stop, devices, orbits, scans, calibrations, reconstructions, jobs):
        app.include_router(module.router)
    return app


def data_path(settings: ServiceSettings) -> Path:
    """Absolute data directory."""
    return settings.data_dir.resolve()
