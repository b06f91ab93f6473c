"""The daemon's HTTP API (FastAPI): devices, scans, downloads, live events, the web page.

`create_app` builds the application for one state dir. Paths are stable (others build on them):
``/api/v1/devices``, ``/api/v1/scans[/{id}[/pause|resume|cancel|reprocess|refine|mesh|recording|
report|events]]``, ``/healthz``, ``/docs`` (OpenAPI, assets served locally), ``/`` (web page).
Errors answer ``{"detail": "<one line>"}``: 401 without the token when one is required, 403 a
state-changing request from another web origin, 404 unknown scan or missing file, 408 a body
that stops coming, 409 busy device or wrong state, 413 body too large, 415 a state-changing
request whose body is not JSON, 422 bad input (or a device or file the operator did not allow),
429 too many scans at once (``Retry-After``).
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import threading
import time
import urllib.parse
from pathlib import Path
from typing import Annotated

from fastapi import APIRouter, Depends, FastAPI, Header, HTTPException, Query, Request
from fastapi import Path as PathParam
from fastapi.exceptions import RequestValidationError
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import FileResponse, JSONResponse, Response, StreamingResponse
from fastapi.staticfiles import StaticFiles
from starlette.concurrency import run_in_threadpool

from . import downloads
from .auth import BearerAuth, LoopbackHostGuard
from .errors import (
    Conflict,
    InvalidRequest,
    OutsideScanFolder,
    TooBusy,
    Unavailable,
    UnknownScan,
)
from .events import SSE_KEEPALIVE, EventHub, sse_message
from .isolation import warm_up
from .jobs import SCANS_DIR, ScanJobs, default_runner_factory
from .limits import BodySizeLimit
from .policy import DEFAULT_MAX_OBJECT_BYTES, DevicePolicy
from .refine import MeshRefiner
from .schemas import SCAN_ID_PATTERN, MeshFormat, RefineRequest, ScanRequest
from .store import JobStore

log = logging.getLogger(__name__)

STATIC = Path(__file__).with_name("static")
DATABASE = "daemon.sqlite3"
ScanId = Annotated[str, PathParam(pattern=SCAN_ID_PATTERN, description="16 hex digits")]
#: SSE ids and offsets: a number a client can hold without overflowing anything (2^53)
MAX_COUNT = 2**53
_STATE_CHANGING = frozenset({"POST", "PUT", "PATCH", "DELETE"})
DISCOVERY_MAX_AGE_S = 10.0
#: Seconds a stopping daemon waits for its first device discovery to end (about a second).
DISCOVERY_WAIT_S = 10.0


def prepare_state_dir(state_dir: Path) -> JobStore:
    """Make the state dir private (0700) and open its job store, repaired or rebuilt from the
    scan folders if damaged (`StoreError`: one line, when it cannot be)."""
    state_dir.mkdir(mode=0o700, parents=True, exist_ok=True)
    if os.stat(state_dir).st_mode & 0o077:
        log.warning("state dir %s was open to others: set to 0700", state_dir)
        os.chmod(state_dir, 0o700)
    return JobStore(state_dir / DATABASE, scans_dir=state_dir / SCANS_DIR)


def create_app(state_dir: str | Path, *, token: str = "", require_token: bool = False,
               runner_factory=default_runner_factory, refiner: MeshRefiner | None = None,
               max_body_bytes: int = 1 << 20, heartbeat_s: float = 15.0,
               loopback_hosts_only: bool = False, allow_devices=(),
               object_dir: str | Path | None = None,
               max_object_bytes: int = DEFAULT_MAX_OBJECT_BYTES,
               object_memory_bytes: int | None = None, max_running: int = 2,
               max_queued: int = 8, body_timeout_s: float = 10.0):
    """The ASGI app (wrapped in the body limits, and with ``loopback_hosts_only`` in
    `LoopbackHostGuard`). The job store opens, and scans left active by a previous process
    become ``interrupted``, when the app starts (lifespan).

    allow_devices, object_dir, max_object_bytes : what requests may name (`DevicePolicy`).
    object_memory_bytes : a scan process's memory budget for loading its object.
    max_running, max_queued : scans without a real device at once, and waiting (then 429).
    """
    state_dir = Path(state_dir)
    auth = BearerAuth(token, require_token)
    policy = DevicePolicy(allow_devices, object_dir, max_object_bytes)

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI):
        store = prepare_state_dir(state_dir)
        if getattr(runner_factory, "func", runner_factory) is default_runner_factory:
            threading.Thread(target=warm_up, name="forkserver-warm-up", daemon=True).start()
        imports = threading.Thread(target=_import_backends, args=(app.state.discovery,),
                                   name="backend-imports", daemon=True)
        imports.start()
        app.state.interrupted_at_start = store.recover()
        if app.state.interrupted_at_start:
            log.warning("scans interrupted by the last stop (resume or re-process them): %s",
                        ", ".join(app.state.interrupted_at_start))
        app.state.jobs = ScanJobs(state_dir, store, EventHub(), runner_factory, refiner,
                                  policy=policy, max_running=max_running,
                                  max_queued=max_queued,
                                  object_memory_bytes=object_memory_bytes)
        try:
            yield
        finally:
            app.state.jobs.shutdown()
            store.close()
            # an interpreter that exits while the thread is inside an SDK's discovery (depthai)
            # aborts (SIGABRT: a daemon stopped within a second of its start exited 134)
            imports.join(timeout=DISCOVERY_WAIT_S)

    app = FastAPI(title="ScanStation daemon", version="1", lifespan=lifespan, docs_url=None,
                  redoc_url=None, description=__doc__)
    app.state.auth = auth
    app.state.discovery = Discovery()
    app.state.heartbeat_s = heartbeat_s
    _add_error_handlers(app)
    app.include_router(_api_router(), prefix="/api/v1",
                       dependencies=[Depends(auth), Depends(same_origin_json)])
    app.mount("/static", StaticFiles(directory=STATIC), name="static")

    @app.get("/healthz", tags=["daemon"])
    async def healthz(request: Request) -> dict:
        """Liveness: answered on the event loop without waiting on any lock or device."""
        jobs: ScanJobs = request.app.state.jobs
        return {"status": "ok", **jobs.counts(),
                "token_required": request.app.state.auth.required}

    @app.get("/", include_in_schema=False)
    def index() -> FileResponse:
        return FileResponse(STATIC / "index.html")

    @app.get("/docs", include_in_schema=False)
    def docs():
        return get_swagger_ui_html(
            openapi_url="/openapi.json", title="ScanStation daemon API",
            swagger_js_url="/static/vendor/swagger-ui-bundle.js",
            swagger_css_url="/static/vendor/swagger-ui.css",
            swagger_favicon_url="/static/favicon.svg")

    limited = BodySizeLimit(app, max_body_bytes, body_timeout_s)
    return LoopbackHostGuard(limited) if loopback_hosts_only else limited


def _import_backends(discovery: Discovery) -> None:
    """Import the serial and simulated backends now, so that the first POST that checks a
    device URL answers in milliseconds too, and discover the devices once."""
    import importlib

    for name in ("drivers.grbl", "sim.camera", "sim.turntable"):
        with contextlib.suppress(ImportError):
            importlib.import_module(name)
    discovery.rows()


class Discovery:
    """Backends and visible devices (`drivers.registry.list_devices`), discovered at most every
    ``max_age_s`` seconds: discovery asks USB and the network (up to a second with an SDK
    installed), and concurrent requests share one discovery instead of each starting theirs."""

    def __init__(self, max_age_s: float = DISCOVERY_MAX_AGE_S):
        self.max_age_s = max_age_s
        self._lock = threading.Lock()
        self._rows: list = []
        self._at = -math.inf

    def rows(self) -> list:
        with self._lock:
            if time.monotonic() - self._at > self.max_age_s:
                from drivers.registry import list_devices

                self._rows, self._at = list_devices(), time.monotonic()
            return self._rows


async def same_origin_json(request: Request) -> None:
    """A state-changing request must come from this daemon's own origin (a browser's
    ``Origin`` matches its ``Host``) and carry JSON or no body: a page on another site can
    send neither, and without CORS headers it cannot read the answer either."""
    if request.method not in _STATE_CHANGING:
        return
    origin = request.headers.get("origin")
    if origin is not None and origin != "null":
        netloc = urllib.parse.urlsplit(origin).netloc.lower()
        if netloc != request.headers.get("host", "").lower():
            raise HTTPException(403, f"cross-origin request from {origin[:100]!r} refused")
    elif origin == "null":
        raise HTTPException(403, "request from an opaque origin refused")
    kind = request.headers.get("content-type", "").split(";")[0].strip().lower()
    has_body = request.headers.get("content-length", "0") not in ("", "0") or \
        "transfer-encoding" in request.headers
    if (kind or has_body) and kind != "application/json":
        raise HTTPException(415, f"this route takes a JSON body (Content-Type: "
                            f"application/json), not {kind or 'an untyped body'!r}")


async def _jobs(request: Request) -> ScanJobs:  # async: no thread hop for a dependency
    return request.app.state.jobs


Jobs = Annotated[ScanJobs, Depends(_jobs)]


def _public(jobs: ScanJobs, record, files: bool = False) -> dict:
    data = record.to_public()
    data["reason"] = jobs.clean(data["reason"])
    if files:
        data["files"] = downloads.available(jobs.scan_dir(record),
                                            record.mesh_params.get("file"))
    return data


def _api_router() -> APIRouter:
    api = APIRouter()

    @api.get("/devices", tags=["devices"])
    def devices(jobs: Jobs, request: Request) -> dict:
        """Every backend (status, visible devices; discovered at most every
        ``DISCOVERY_MAX_AGE_S`` s) and the devices held by running scans."""
        busy = jobs.busy_devices()
        backends = [{"kind": kind, "scheme": scheme, "status": status, "urls": urls}
                    for kind, scheme, status, urls in request.app.state.discovery.rows()]
        return {"backends": backends,
                "busy": [{"device": key, "scan": scan} for key, scan in sorted(busy.items())]}

    @api.post("/scans", status_code=201, tags=["scans"])
    def create_scan(body: ScanRequest, jobs: Jobs) -> dict:
        """Start a scan from a plan and device URLs (none: the simulated station). Answers at
        once: ``starting`` (its process opens the devices) or ``queued`` (the daemon already
        runs its limit of scans); 429 when the queue is full too."""
        return _public(jobs, jobs.create(body))

    @api.get("/scans", tags=["scans"])
    def list_scans(jobs: Jobs, limit: Annotated[int, Query(ge=1, le=1000)] = 100,
                   offset: Annotated[int, Query(ge=0, le=MAX_COUNT)] = 0) -> dict:
        return {"scans": [_public(jobs, r) for r in jobs.list(limit, offset)]}

    @api.get("/scans/{scan_id}", tags=["scans"])
    async def get_scan(scan_id: ScanId, jobs: Jobs) -> dict:
        """The scan with its ``state``, ``progress`` and downloadable ``files`` (answered from
        memory on the event loop: status polls stay fast while scans run)."""
        return _public(jobs, jobs.get(scan_id), files=True)

    @api.get("/scans/{scan_id}/plan", tags=["scans"])
    def get_plan(scan_id: ScanId, jobs: Jobs) -> dict:
        """The scan's whole plan, angles included (the scan's JSON has ``n_views`` only)."""
        return jobs.get(scan_id).request.get("plan") or {}

    @api.delete("/scans/{scan_id}", status_code=204, tags=["scans"])
    def delete_scan(scan_id: ScanId, jobs: Jobs) -> Response:
        jobs.delete(scan_id)
        return Response(status_code=204)

    @api.post("/scans/{scan_id}/pause", status_code=202, tags=["scans"])
    def pause_scan(scan_id: ScanId, jobs: Jobs) -> dict:
        """Pause at the next safe point (between frames or views)."""
        return _public(jobs, jobs.pause(scan_id))

    @api.post("/scans/{scan_id}/resume", status_code=202, tags=["scans"])
    def resume_scan(scan_id: ScanId, jobs: Jobs) -> dict:
        """Resume a paused scan, or an interrupted one from its last completed view."""
        return _public(jobs, jobs.resume(scan_id))

    @api.post("/scans/{scan_id}/cancel", status_code=202, tags=["scans"])
    def cancel_scan(scan_id: ScanId, jobs: Jobs) -> dict:
        """Stop after the current step; the recording keeps every completed view."""
        return _public(jobs, jobs.cancel(scan_id))

    @api.post("/scans/{scan_id}/reprocess", status_code=202, tags=["scans"])
    def reprocess_scan(scan_id: ScanId, jobs: Jobs) -> dict:
        """Rebuild the mesh and report from the recording alone (no devices)."""
        return _public(jobs, jobs.reprocess(scan_id))

    @api.post("/scans/{scan_id}/refine", tags=["scans"])
    def remesh_scan(scan_id: ScanId, body: RefineRequest, jobs: Jobs) -> dict:
        """A new mesh version with a new λ / boundary depth, through ONNX (no retraining)."""
        return _public(jobs, jobs.remesh(scan_id, body.lam, body.depth), files=True)

    @api.get("/scans/{scan_id}/mesh", tags=["downloads"])
    def get_mesh(scan_id: ScanId, jobs: Jobs, format: MeshFormat = "ply") -> Response:
        record = jobs.get(scan_id)
        path = downloads.mesh_file(jobs.scan_dir(record), record.mesh_params.get("file"))
        name = f"scan-{scan_id}-v{record.mesh_version}.{format}"
        headers = {"Content-Disposition": f'attachment; filename="{name}"',
                   "Cache-Control": "no-store"}
        return Response(downloads.mesh_bytes(path, format), headers=headers,
                        media_type=downloads.MEDIA_TYPES[format])

    @api.get("/scans/{scan_id}/recording", tags=["downloads"])
    def get_recording(scan_id: ScanId, jobs: Jobs,
                      segment: Annotated[int, Query(ge=1, le=10_000)] = 1) -> FileResponse:
        """One MCAP segment (a resumed scan has one per run: 1, 2, …)."""
        path = downloads.recording_file(jobs.scan_dir(jobs.get(scan_id)), segment)
        return FileResponse(path, media_type="application/octet-stream",
                            filename=f"scan-{scan_id}-{path.name}")

    @api.get("/scans/{scan_id}/report", tags=["downloads"])
    def get_report(scan_id: ScanId, jobs: Jobs) -> FileResponse:
        path = downloads.report_file(jobs.scan_dir(jobs.get(scan_id)))
        return FileResponse(path, media_type="application/json",
                            filename=f"scan-{scan_id}.json")

    @api.get("/scans/{scan_id}/events", tags=["events"])
    async def scan_events(
        scan_id: ScanId, request: Request,
        last_event_id: Annotated[str | None, Header(max_length=40)] = None,
        after: Annotated[int, Query(ge=0, le=MAX_COUNT,
                                    description="skip documents up to this id")] = 0,
    ) -> StreamingResponse:
        """Server-Sent Events: the scan's documents (``data``: JSON with ``kind``), numbered
        (``id``); the stream ends when the scan does. Reconnecting with ``Last-Event-ID``
        resumes after the last document received."""
        jobs: ScanJobs = request.app.state.jobs
        if last_event_id is not None and last_event_id.strip():
            text = last_event_id.strip()
            if not (text.isascii() and text.isdigit() and int(text) <= MAX_COUNT):
                raise InvalidRequest(f"Last-Event-ID must be a document id (0 to {MAX_COUNT})")
            after = max(after, int(text))
        channel = await run_in_threadpool(jobs.channel, scan_id)  # takes the jobs lock
        heartbeat = request.app.state.heartbeat_s

        async def stream():
            yield b"retry: 2000\n\n"
            async for item in channel.stream(after, heartbeat):
                yield SSE_KEEPALIVE if item is None else sse_message(*item)

        return StreamingResponse(stream(), media_type="text/event-stream",
                                 headers={"Cache-Control": "no-store", "X-Accel-Buffering": "no"})

    return api


def _add_error_handlers(app: FastAPI) -> None:
    def reply(status: int):
        async def handler(request: Request, exc: Exception) -> JSONResponse:
            return JSONResponse({"detail": str(exc)}, status_code=status)
        return handler

    app.add_exception_handler(UnknownScan, reply(404))
    app.add_exception_handler(Unavailable, reply(404))
    app.add_exception_handler(OutsideScanFolder, reply(404))
    app.add_exception_handler(Conflict, reply(409))
    app.add_exception_handler(InvalidRequest, reply(422))

    async def too_busy(request: Request, exc: TooBusy) -> JSONResponse:
        return JSONResponse({"detail": str(exc)}, status_code=429,
                            headers={"Retry-After": str(exc.retry_after_s)})

    app.add_exception_handler(TooBusy, too_busy)

    async def invalid(request: Request, exc: RequestValidationError) -> JSONResponse:
        errors = exc.errors()
        lines = [f"{'.'.join(str(p) for p in e['loc'])}: {e['msg']}" for e in errors]
        return JSONResponse({"detail": "; ".join(lines) or "invalid request",
                             "errors": [{"loc": e["loc"], "msg": e["msg"]} for e in errors]},
                            status_code=422)

    app.add_exception_handler(RequestValidationError, invalid)
