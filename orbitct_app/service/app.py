"""The FastAPI application factory: ``create_app(settings)`` builds the service, its lifespan and the routers."""

from __future__ import annotations

from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import FastAPI

from orbitct import __version__
from orbitct_app.console.pages import install_console
from orbitct_app.service.core.errors import ContentLengthLimit, install_error_handlers
from orbitct_app.service.core.settings import ServiceSettings
from orbitct_app.service.routers import (
    calibrations,
    devices,
    geometry,
    health,
    jobs,
    orbits,
    pacs,
    people,
    plans,
    reconstructions,
    scans,
    session,
    stop,
    surfaces,
)
from orbitct_app.service.state import Service

TAGS = [
    {"name": "stop", "description": "Emergency stop: every axis halted, X-rays off. Any valid token."},
    {"name": "devices", "description": "Bench devices: state, referencing, maintenance moves (operator)."},
    {"name": "orbits", "description": "Orbit kinds, parameter schemas, validation and previews."},
    {"name": "scans", "description": "Acquisitions on the bench, one at a time (operator starts and aborts)."},
    {"name": "calibrations", "description": "Geometric calibration from BBs (analyst)."},
    {"name": "reconstructions", "description": "FDK and PWLS reconstruction (analyst)."},
    {"name": "geometry", "description": "A scan's per-view geometry for other reconstruction toolkits."},
    {"name": "jobs", "description": "State, progress, log and cancellation of calibration and reconstruction jobs."},
    {
        "name": "pacs",
        "description": "The DICOM nodes of the settings: find series, import C-arm runs, send volumes (analyst).",
    },
    {
        "name": "plans",
        "description": "BB plans: where to tape the BBs for an object and orbit, with the predicted accuracy per view, and the objects' surfaces uploaded as meshes to plan on (analyst creates).",
    },
    {
        "name": "session",
        "description": "The web console's sign-in: a token exchanged for a session cookie (CSRF-protected).",
    },
    {"name": "people", "description": "Who may sign in, with which roles (operator manages)."},
    {"name": "health", "description": "Liveness, no token needed."},
]


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
            "(tokens from `orbitct token create --role operator|analyst|viewer`), or the web console's session "
            "cookie from `POST /session` (then `X-CSRF-Token` with every POST). The console is at `/`. Errors are JSON "
            "`{error, message, details: [{field, reason}]}`. Progress streams are server-sent events."
        ),
        openapi_tags=TAGS,
        lifespan=lifespan,
        docs_url=None,  # served by the console from orbitct's own copies of Swagger UI and ReDoc (no CDN)
        redoc_url=None,
    )
    app.state.service = svc
    install_error_handlers(app)
    app.add_middleware(
        ContentLengthLimit, max_bytes=settings.max_body_bytes, larger={"/surfaces": settings.max_upload_bytes}
    )
    for module in (
        health,
        session,
        stop,
        devices,
        orbits,
        scans,
        calibrations,
        reconstructions,
        geometry,
        jobs,
        pacs,
        plans,
        surfaces,
        people,
    ):
        app.include_router(module.router)
    install_console(app)
    return app
