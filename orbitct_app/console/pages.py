"""The console's pages, its static files and the offline API docs, added to the REST application.

Pages are Jinja2 templates rendered for the signed-in user (controls the role may not use are not
rendered; the API refuses them anyway). Everything a page shows or does goes through the REST API
from the browser (``static/console.js``) with the session cookie and its CSRF token; no page
handler reads or changes the bench itself.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any
from urllib.parse import quote

from fastapi import APIRouter, FastAPI, Query, Request
from fastapi import Path as PathParam
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html
from fastapi.responses import HTMLResponse, RedirectResponse, Response
from fastapi.staticfiles import StaticFiles
from fastapi.templating import Jinja2Templates

from orbitct import __version__
from orbitct.livewarnings import ABORT_KINDS, WARNING_MEANINGS
from orbitct_app.service.core.auth import PERMISSIONS, ROLE_WORDS
from orbitct_app.service.core.sessions import COOKIE

HERE = Path(__file__).resolve().parent
STATIC = HERE / "static"
VENDOR = "/static/vendor"
SWAGGER = f"{VENDOR}/swagger-ui-5.35.0"
REDOC = f"{VENDOR}/redoc-2.5.4"
# Pages load only what orbitct serves; the 3-D viewer needs blob: workers and WebAssembly (NIfTI decompression).
CSP = (
    "default-src 'self'; img-src 'self' data: blob:; style-src 'self' 'unsafe-inline'; script-src 'self' "
    "'wasm-unsafe-eval'; worker-src 'self' blob:; connect-src 'self' blob: data:; font-src 'self'; "
    "frame-ancestors 'none'; base-uri 'none'; form-action 'self'"
)
# The API docs pages keep FastAPI's inline start-up script; nothing outside orbitct may load (ReDoc's footer logo
# would come from its CDN: blocked, the logo hides itself).
DOCS_CSP = (
    "default-src 'self'; script-src 'self' 'unsafe-inline'; style-src 'self' 'unsafe-inline'; img-src 'self' data: "
    "blob:; worker-src 'self' blob:; connect-src 'self'; font-src 'self' data:; frame-ancestors 'none'"
)
NAV = [
    ("bench", "Bench", "/console/bench"),
    ("scan-new", "New scan", "/console/scans/new"),
    ("scans", "Scans", "/console/scans"),
    ("jobs", "Jobs", "/console/jobs"),
    ("plans", "BB plans", "/console/plans"),
]

templates = Jinja2Templates(directory=str(HERE / "templates"))
router = APIRouter(include_in_schema=False)
Id = Annotated[str, PathParam(pattern=r"^[A-Za-z0-9_-]{1,64}$")]  # a scan or job id as the API makes them


def _render(request: Request, template: str, page: str, title: str, **context: Any) -> Response:
    """A page for the signed-in user, or a redirect to the sign-in page."""
    signed_in = request.app.state.service.sessions.lookup(request.cookies.get(COOKIE, ""))
    if signed_in is None:
        return RedirectResponse(f"/sign-in?next={quote(request.url.path)}", status_code=303)
    session, principal = signed_in
    may = {p: principal.may(p) for p in sorted(set().union(*PERMISSIONS.values()))}
    response = templates.TemplateResponse(
        request,
        template,
        {
            "page": page,
            "title": title,
            "user": principal,
            "may": may,
            "csrf": session.csrf,
            "nav": NAV,
            "version": __version__,
            **context,
        },
    )
    _secure(response)
    return response


def _secure(response: Response) -> None:
    response.headers["Content-Security-Policy"] = CSP
    response.headers["X-Content-Type-Options"] = "nosniff"
    response.headers["Referrer-Policy"] = "same-origin"
    response.headers["Cache-Control"] = "no-store"


@router.get("/")
def home() -> Response:
    """The console starts at the bench."""
    return RedirectResponse("/console/bench", status_code=303)


@router.get("/sign-in", response_class=HTMLResponse)
def sign_in(request: Request, next: str = "/console/bench") -> Response:
    """Sign in with a token (posted to ``/session`` by the page's script, never in a URL)."""
    target = next if next.startswith("/console/") and len(next) < 200 else "/console/bench"
    response = templates.TemplateResponse(
        request, "sign_in.html", {"title": "Sign in", "next": target, "version": __version__}
    )
    _secure(response)
    return response


@router.get("/console/bench", response_class=HTMLResponse)
def bench(request: Request) -> Response:
    """Devices, their state, referencing and maintenance moves, the emergency-stop latch."""
    return _render(request, "bench.html", "bench", "Bench")


@router.get("/console/scans/new", response_class=HTMLResponse)
def scan_new(request: Request) -> Response:
    """Orbit, parameters, preview and pre-flight, then start."""
    return _render(
        request,
        "scan_new.html",
        "scan-new",
        "New scan",
        abort_kinds=[(kind, WARNING_MEANINGS[kind]) for kind in ABORT_KINDS],
    )


@router.get("/console/scans", response_class=HTMLResponse)
def scans(request: Request) -> Response:
    """Scans with their state, filterable."""
    return _render(request, "scans.html", "scans", "Scans")


@router.get("/console/scans/{scan_id}", response_class=HTMLResponse)
def scan(request: Request, scan_id: Id) -> Response:
    """One scan: live progress while it runs, then its summary, jobs and downloads."""
    return _render(request, "scan.html", "scan", "Scan", scan_id=scan_id)


@router.get("/console/calibrations/{job_id}", response_class=HTMLResponse)
def calibration(request: Request, job_id: Id) -> Response:
    """A calibration's report: the Table 1 figures, RPE per iteration, corrections per view."""
    return _render(request, "calibration.html", "calibration", "Calibration report", job_id=job_id)


@router.get("/console/reconstructions/{job_id}", response_class=HTMLResponse)
def viewer(
    request: Request, job_id: Id, compare: Annotated[str, Query(pattern=r"^[A-Za-z0-9_-]{0,64}$")] = ""
) -> Response:
    """Slices and 3-D of a reconstruction, beside another of the same scan with the same window."""
    return _render(request, "viewer.html", "viewer", "Volume viewer", job_id=job_id, compare=compare)


@router.get("/console/people", response_class=HTMLResponse)
def people(request: Request) -> Response:
    """Operators: who may sign in, with which roles; add and remove people."""
    return _render(request, "people.html", "people", "People", roles=ROLE_WORDS)


@router.get("/console/jobs", response_class=HTMLResponse)
def jobs(request: Request) -> Response:
    """Calibration and reconstruction jobs: queue, progress, log, cancel."""
    return _render(request, "jobs.html", "jobs", "Jobs")


@router.get("/console/plans", response_class=HTMLResponse)
def plans(request: Request) -> Response:
    """Plan where to tape the BBs (analysts), and the plans made so far."""
    return _render(request, "plans.html", "plans", "BB plans")


def install_console(app: FastAPI) -> None:
    """Serve the console's pages and static files, and ``/docs`` and ``/redoc`` from orbitct's own copies."""
    app.mount("/static", StaticFiles(directory=str(STATIC)), name="static")
    app.include_router(router)
    openapi_url = app.openapi_url or "/openapi.json"

    @app.get("/docs", include_in_schema=False)
    def swagger() -> HTMLResponse:
        page = get_swagger_ui_html(
            openapi_url=openapi_url,
            title=f"{app.title} API",
            swagger_js_url=f"{SWAGGER}/swagger-ui-bundle.js",
            swagger_css_url=f"{SWAGGER}/swagger-ui.css",
            swagger_favicon_url="/static/favicon.svg",
            swagger_ui_parameters={"validatorUrl": None},
        )
        page.headers["Content-Security-Policy"] = DOCS_CSP
        return page

    @app.get("/redoc", include_in_schema=False)
    def redoc() -> HTMLResponse:
        page = get_redoc_html(
            openapi_url=openapi_url,
            title=f"{app.title} API",
            redoc_js_url=f"{REDOC}/redoc.standalone.js",
            redoc_favicon_url="/static/favicon.svg",
            with_google_fonts=False,
        )
        page.headers["Content-Security-Policy"] = DOCS_CSP
        return page
