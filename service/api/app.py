"""The HTTP side port (docs/contract.md §2).  The lifespan owns the Zenoh node and its worker."""

from __future__ import annotations

import hashlib
import hmac
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from typing import Annotated, Any, Literal
from urllib.parse import parse_qsl, quote, unquote, urlencode

from fastapi import FastAPI, HTTPException, Query, Request
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html, get_swagger_ui_oauth2_redirect_html
from fastapi.responses import HTMLResponse, JSONResponse, RedirectResponse, Response
from fastapi.staticfiles import StaticFiles
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest
from starlette.requests import cookie_parser
from starlette.types import ASGIApp, Receive, Scope, Send

from service.api.deps import NodeDep
from service.api.limits import HttpLimits
from service.api.metrics import registry_for
from service.api.picture import add_picture
from service.schema_files import EXAMPLES
from service.transport.node import ServiceNode
from service.wire.models import (
    BiasEstimate,
    PairSet,
    RadarInfo,
    RadarPerformance,
    Status,
    SystemTrackBatch,
    TrackBatch,
)

StatusFilter = Literal["confirmed", "tentative", "all"]


#: Where the Swagger UI and ReDoc bundles are served from (and the picture's own files).
DOCS_ASSETS = "/static/docs"
PICTURE_ASSETS = "/static"
#: /docs and /redoc load nothing from another host (Swagger UI's start-up script is inline;
#: both bundles compile JSON Schema validators at run time and start workers from blobs).
DOCS_CSP = (
    "default-src 'self'; script-src 'self' 'unsafe-inline' 'unsafe-eval' blob:; "
    "style-src 'self' 'unsafe-inline'; img-src 'self' data: blob:; font-src 'self' data:; "
    "worker-src 'self' blob:; connect-src 'self'; base-uri 'self'; form-action 'self'"
)


def add_offline_docs(app: FastAPI) -> None:
    """``/docs``, its OAuth2 redirect and ``/redoc`` with every script, style and icon served by
    the service itself (FastAPI's defaults load them from a CDN, and ReDoc its fonts from Google:
    blank pages in a room without Internet).

    The bundles come from the ``fastapi-offline`` package (its ``static/`` folder only; its app
    factory is not used): MIT, with Swagger UI 5.32 (Apache-2.0) and ReDoc 2.5 (MIT) inside;
    maintained (23 releases, 1.7.7 in June 2026); a 0.8 MB wheel that needs nothing but
    FastAPI and supports Python 3.8 on.  ``fastapi-standalone-docs`` ships the upstream
    licence files too but needs Python 3.11 (the runtime supports 3.10) and FastAPI 0.133 on;
    ``swagger-ui-bundle`` has no ReDoc and an old Swagger UI (4.15, 2023).
    Swagger UI's online validator badge is off (``validatorUrl: null``): it would ask an
    outside host.  ReDoc 2 shows Redocly's logo from Redocly's CDN whatever its options: the
    pages' Content-Security-Policy (``DOCS_CSP``) keeps that request, and any other to another
    host, in the browser.
    """
    app.mount(DOCS_ASSETS, StaticFiles(packages=[("fastapi_offline", "static")]), name="docs-static")
    favicon = f"{DOCS_ASSETS}/favicon.png"

    def root(request: Request) -> str:
        return str(request.scope.get("root_path", "")).rstrip("/")

    async def swagger_ui(request: Request) -> HTMLResponse:
        r = root(request)
        page = get_swagger_ui_html(
            openapi_url=f"{r}{app.openapi_url}",
            title=f"{app.title} - Swagger UI",
            swagger_js_url=f"{r}{DOCS_ASSETS}/swagger-ui-bundle.js",
            swagger_css_url=f"{r}{DOCS_ASSETS}/swagger-ui.css",
            swagger_favicon_url=f"{r}{favicon}",
            oauth2_redirect_url=f"{r}/docs/oauth2-redirect",
            swagger_ui_parameters={"validatorUrl": None},
        )
        page.headers["Content-Security-Policy"] = DOCS_CSP
        return page

    async def oauth2_redirect(request: Request) -> HTMLResponse:
        return get_swagger_ui_oauth2_redirect_html()

    async def redoc(request: Request) -> HTMLResponse:
        r = root(request)
        page = get_redoc_html(
            openapi_url=f"{r}{app.openapi_url}",
            title=f"{app.title} - ReDoc",
            redoc_js_url=f"{r}{DOCS_ASSETS}/redoc.standalone.js",
            redoc_favicon_url=f"{r}{favicon}",
            with_google_fonts=False,
        )
        page.headers["Content-Security-Policy"] = DOCS_CSP
        return page

    # Plain routes, out of the OpenAPI document, as FastAPI's own docs routes are.
    app.add_route("/docs", swagger_ui, include_in_schema=False)
    app.add_route("/docs/oauth2-redirect", oauth2_redirect, include_in_schema=False)
    app.add_route("/redoc", redoc, include_in_schema=False)


#: What a probe or a load balancer calls without credentials (contract §4.6).
OPEN_PATHS = frozenset({"/healthz", "/readyz"})
#: A browser can add no header to a page load or to an EventSource: ``GET /picture?token=...``
#: trades the token for a cookie that the page's own requests (its script, styles and feed)
#: then carry, and sends the browser on to the address without it.
PICTURE_PATH = "/picture"
#: The picture's feed: a long response, bounded by its own cap (``picture_max_clients``).
PICTURE_EVENTS_PATH = "/picture/events"
TOKEN_QUERY = "token"
TOKEN_COOKIE = "topofusion_token"


def _route_path(scope: Scope) -> str:
    """The path the app routes on: without the server's ``root_path`` (as Starlette strips it)."""
    path: str = scope["path"]
    root: str = scope.get("root_path", "")
    if root and path.startswith(root) and path[len(root) : len(root) + 1] in ("", "/"):
        return path[len(root) :]
    return path


class BearerTokenMiddleware:
    """Every request but :data:`OPEN_PATHS` needs ``Authorization: Bearer <token>`` or the
    picture's cookie (:data:`TOKEN_COOKIE`); anything else is 401 with ``WWW-Authenticate: Bearer``.

    Plain ASGI rather than Starlette's ``BaseHTTPMiddleware``: it wraps the mounted static apps
    as well as the routes, and it hands the response through untouched, so that the picture's
    server-sent events keep streaming.  Both sides are hashed (SHA-256) before
    ``hmac.compare_digest``: the time a comparison takes says nothing about the token, not even
    its length.  The token is never logged.
    """

    def __init__(self, app: ASGIApp, token: str) -> None:
        if not token:
            raise ValueError("an empty API token would let anyone in")
        self.app = app
        self._digest = hashlib.sha256(token.encode()).digest()

    def _valid(self, given: bytes) -> bool:
        return hmac.compare_digest(hashlib.sha256(given).digest(), self._digest)

    def _presented(self, scope: Scope) -> list[bytes]:
        """The credentials a request carries: a bearer token and the picture's cookie."""
        out = []
        for name, value in scope["headers"]:
            if name == b"authorization":
                scheme, _, credentials = value.strip().partition(b" ")
                if scheme.lower() == b"bearer":
                    out.append(credentials.strip())
            elif name == b"cookie":
                cookie = cookie_parser(value.decode("latin-1")).get(TOKEN_COOKIE)
                if cookie is not None:
                    out.append(unquote(cookie).encode())
        return out

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] not in ("http", "websocket"):  # the lifespan
            await self.app(scope, receive, send)
            return
        path = _route_path(scope)
        if path in OPEN_PATHS:
            await self.app(scope, receive, send)
            return
        if scope["type"] == "http" and scope["method"] == "GET" and path == PICTURE_PATH:
            query = parse_qsl(scope["query_string"].decode("latin-1"), keep_blank_values=True)
            given = [v for k, v in query if k == TOKEN_QUERY]
            if given:
                if len(given) == 1 and self._valid(given[0].encode()):
                    rest = [(k, v) for k, v in query if k != TOKEN_QUERY]
                    await self._to_cookie(scope, given[0], rest)(scope, receive, send)
                else:
                    await self._refuse(scope, "invalid token", receive, send)
                return
        presented = self._presented(scope)
        # every credential is compared, so that a wrong header beside a good cookie costs the same
        if any([self._valid(p) for p in presented]):
            await self.app(scope, receive, send)
            return
        detail = "invalid token" if presented else "missing token: send Authorization: Bearer <token>"
        await self._refuse(scope, detail, receive, send)

    @staticmethod
    def _to_cookie(scope: Scope, token: str, rest: list[tuple[str, str]]) -> Response:
        location = scope.get("root_path", "") + PICTURE_PATH + (f"?{urlencode(rest)}" if rest else "")
        # no-referrer and no-store: the address that held the token goes nowhere else
        response = RedirectResponse(
            location, status_code=303, headers={"Cache-Control": "no-store", "Referrer-Policy": "no-referrer"}
        )
        response.set_cookie(
            TOKEN_COOKIE,
            quote(token, safe=""),  # any token, as cookie-safe characters
            path="/",
            httponly=True,  # out of reach of scripts
            samesite="strict",  # never sent with another site's requests
            secure=scope.get("scheme") == "https",
        )
        return response

    @staticmethod
    async def _refuse(scope: Scope, detail: str, receive: Receive, send: Send) -> None:
        if scope["type"] == "websocket":
            await send({"type": "websocket.close", "code": 1008, "reason": "unauthorized"})
            return
        response = JSONResponse(
            {"detail": detail},
            status_code=401,
            headers={"WWW-Authenticate": "Bearer", "Cache-Control": "no-store"},
        )
        await response(scope, receive, send)


class RequestLimitMiddleware:
    """At most ``max_requests`` requests in progress at once; beyond, 503 with ``Retry-After``
    at once (``TOPOFUSION_HTTP_MAX_REQUESTS``).

    The probes (:data:`OPEN_PATHS`) are never counted nor refused: they answer from the event
    loop without work, and they must answer whatever else is asked.  The picture's feed has
    its own cap (a stream lasts minutes and holds no thread).  The synchronous endpoints run
    on a pool of threads; without this bound a burst of slow requests would queue there
    without end, and every later request behind them.
    """

    def __init__(self, app: ASGIApp, max_requests: int) -> None:
        self.app = app
        self.max_requests = max_requests
        self.active = 0
        self.refused = 0

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or _route_path(scope) in OPEN_PATHS | {PICTURE_EVENTS_PATH}:
            await self.app(scope, receive, send)
            return
        if self.active >= self.max_requests:
            self.refused += 1
            busy = JSONResponse(
                {"detail": "too many requests in progress; try again"},
                status_code=503,
                headers={"Retry-After": "1", "Cache-Control": "no-store"},
            )
            await busy(scope, receive, send)
            return
        self.active += 1
        try:
            await self.app(scope, receive, send)
        finally:
            self.active -= 1


def _document_bearer(app: FastAPI) -> None:
    """The OpenAPI document says which operations need the token (Swagger UI's "Authorize")."""
    plain = app.openapi

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            schema = plain()
            schemes = schema.setdefault("components", {}).setdefault("securitySchemes", {})
            schemes["bearer"] = {"type": "http", "scheme": "bearer"}
            for path, operations in schema.get("paths", {}).items():
                if path in OPEN_PATHS:
                    continue
                for operation in operations.values():
                    operation["security"] = [{"bearer": []}]
                    operation.setdefault("responses", {})["401"] = {"description": "no valid token"}
            app.openapi_schema = schema
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]


def _example(example: Any, **errors: str) -> dict[int | str, dict[str, Any]]:
    """``responses=`` of a route: its 200 answer's example (the contract's own, as in
    ``schemas/examples``) and its documented errors (``e404="unknown radar"``)."""
    out: dict[int | str, dict[str, Any]] = {200: {"content": {"application/json": {"example": example}}}}
    out.update({int(code[1:]): {"description": text} for code, text in errors.items()})
    return out


def create_app(
    node_factory: Callable[[], ServiceNode],
    on_started: Callable[[ServiceNode], None] | None = None,
    on_stopping: Callable[[ServiceNode], None] | None = None,
    *,
    api_token: str | None = None,
    limits: HttpLimits | None = None,
) -> FastAPI:
    """An app whose lifespan starts ``node_factory()`` and stops it on shutdown.

    ``on_started`` / ``on_stopping`` run right after the node starts and right before it
    stops (the demo starts and stops its simulator there).  ``api_token``
    (``TOPOFUSION_API_TOKEN``): every endpoint but ``/healthz`` and ``/readyz`` needs it
    (:class:`BearerTokenMiddleware`); ``None`` or empty (an unset variable that compose passes
    through as ``""``): none does.  ``limits`` (``TOPOFUSION_HTTP_*``; default: the settings'
    defaults): the requests in progress and the picture's viewers; the server applies the
    rest (service/api/server.py).
    """
    limits = limits or HttpLimits()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        node = node_factory()
        node.start()
        app.state.node = node
        app.state.registry = registry_for(node)
        if on_started is not None:
            on_started(node)
        try:
            yield
        finally:
            feed.close()
            if on_stopping is not None:
                on_stopping(node)
            node.stop()
            app.state.stopped = True

    app = FastAPI(
        title="TopoFusion",
        version="0.1.0",
        summary="Radar track correlation under unknown sensor bias (SVD topology sequences)",
        lifespan=lifespan,
        docs_url=None,
        redoc_url=None,
    )
    add_offline_docs(app)

    # The probes are coroutines: they answer from the event loop, never waiting for one of
    # the threads the other endpoints run on (all of which a burst may hold).
    @app.get(
        "/healthz",
        summary="Liveness: the process answers",
        description="200 while the process runs; needs no token and answers under connection floods "
        "(the probes run on the event loop). Use it for a liveness probe. HEAD answers as GET, "
        "without the body.",
        responses=_example({"status": "ok"}),
    )
    async def healthz() -> dict[str, str]:
        return {"status": "ok"}

    @app.get(
        "/readyz",
        summary="Readiness: Zenoh connected, worker running, outputs live",
        description="200 once the Zenoh session is open and the worker runs; 503 with a `reason`: "
        "`starting`, `connecting to zenoh`, `no zenoh connection`, `worker stalled`, `partition mismatch: "
        "...` (partitioned: a worker of another N or salt), `worker not "
        "running`, `shutting down`, or `outputs stale: the data clock has not moved for N s` (the "
        "feed stopped or every input is refused; /status `feed` says more). Needs no token.",
        responses={
            **_example({"status": "ready"}),
            503: {
                "description": "not ready, and why",
                "content": {
                    "application/json": {"example": {"status": "not ready", "reason": "no zenoh connection"}}
                },
            },
        },
    )
    async def readyz(request: Request) -> JSONResponse:
        node: ServiceNode | None = getattr(request.app.state, "node", None)
        if node is None or not node.ready:
            reason = "starting" if node is None else (node.not_ready_reason or "worker not running")
            return JSONResponse({"status": "not ready", "reason": reason}, status_code=503)
        return JSONResponse({"status": "ready"})

    # HEAD answers as GET without the body (a load balancer's probe, `curl -I`), the same
    # endpoints, kept out of the OpenAPI document (one operation a path and method there)
    for path, probe in (("/healthz", healthz), ("/readyz", readyz)):
        app.add_api_route(path, probe, methods=["HEAD"], include_in_schema=False)

    @app.get(
        "/status",
        response_model=Status,
        summary="The service's status: radars, pairs, correlation timings, queue, feed",
        description="Per radar its counters and data clock; pairs confirmed and tentative; the "
        "correlation's update times and `pending`; `outputs_time_s`, the data time through which "
        "every output is complete; the ingest queue and its drops by key; the feed (stale outputs, "
        "outages); with --state-dir the state writes; partitioned, the whole network's. The same "
        "JSON as `get {prefix}/status` over Zenoh.",
        responses=_example(EXAMPLES["Status"]),
    )
    def status(node: NodeDep) -> dict[str, Any]:
        return node.status()

    @app.get(
        "/radars",
        response_model=list[RadarInfo],
        summary="Every radar whose site is known, with its counters",
        description="The `RadarSite` fields plus batches, plots, rejected, lost batches (from `seq` "
        "gaps) and the radar's data clock `last_time_s`.",
        responses=_example([EXAMPLES["RadarInfo"]]),
    )
    def radars(node: NodeDep) -> list[dict[str, Any]]:
        return node.radars()

    @app.get(
        "/radars/{radar_id}/tracks",
        response_model=TrackBatch,
        summary="A radar's tracks (confirmed by default)",
        description="The radar's latest `TrackBatch`, as published on `{prefix}/radar/{id}/tracks`: "
        "every track's position and velocity in ECEF and geodetic, its status, Mode S and Mode 3/A "
        "when known. `status`: `confirmed` (default), `tentative` or `all`.",
        responses=_example(EXAMPLES["TrackBatch"], e404="unknown radar"),
    )
    def tracks(node: NodeDep, radar_id: str, status: StatusFilter = "confirmed") -> dict[str, Any]:
        batch = node.snapshot.track_batch(radar_id, status)
        if batch is None:
            raise HTTPException(status_code=404, detail=f"unknown radar {radar_id!r}")
        return batch

    @app.get(
        "/radars/{radar_id}/performance",
        response_model=RadarPerformance,
        summary="A radar's live performance against the ADS-B / AIS references",
        description="Over a sliding window of data time (`TOPOFUSION_PERFORMANCE_WINDOW_S`, default "
        "600 s), measured against the reference aircraft paired with the radar's tracks: detection "
        "probability (with its binomial 1-sigma, scans expected in the learnt coverage and detected), "
        "horizontal position error (RMS and median after compensating the biases the window estimates, "
        "RMS before; range and azimuth RMS), Mode 3/A and Mode C correctness, the requirements and the "
        "verdict. Any figure without data is null; docs/assessment.md says how each is measured.",
        responses=_example(EXAMPLES["RadarPerformance"], e404="unknown radar"),
    )
    def performance(node: NodeDep, radar_id: str) -> dict[str, Any]:
        figures = node.radar_performance(radar_id)
        if figures is None:
            raise HTTPException(status_code=404, detail=f"unknown radar {radar_id!r}")
        return figures

    @app.get(
        "/pairs",
        response_model=list[PairSet],
        summary="Correlated track pairs, per radar pair",
        description="Every pair set (two radars, or a radar and a reference source) with its pairs, "
        "their scores and status. `radar_a` / `radar_b` (either order; one of them: every pair set "
        "of that radar) and `status` (`confirmed` default, `tentative`, `all`) filter. Every pair "
        "names tracks the same snapshot holds.",
        responses=_example([EXAMPLES["PairSet"]]),
    )
    def pairs(
        node: NodeDep,
        radar_a: Annotated[str | None, Query()] = None,
        radar_b: Annotated[str | None, Query()] = None,
        status: StatusFilter = "confirmed",
    ) -> list[dict[str, Any]]:
        return node.pair_sets(radar_a, radar_b, status)

    @app.get(
        "/system-tracks",
        response_model=SystemTrackBatch,
        summary="The fused picture: one system track per aircraft",
        description="Radar tracks that correlate (directly or through other radars) form one system "
        "track, bias-compensated and fused from its members; its id stays with the aircraft while "
        "any member lives. `status`: `confirmed` (default), `tentative`, `all`. Partitioned, worker 1 "
        "draws it: another worker answers 503 while worker 1 does not answer.",
        responses=_example(
            EXAMPLES["SystemTrackBatch"], e503="partitioned: worker 1, which draws it, does not answer"
        ),
    )
    def system_tracks(node: NodeDep, status: StatusFilter = "confirmed") -> dict[str, Any]:
        picture = node.system_tracks(status)
        if picture is None:  # partitioned: worker 1 draws it, and it does not answer now
            raise HTTPException(
                status_code=503,
                detail="the picture is drawn by worker 1, which does not answer",
                headers={"Retry-After": "2"},
            )
        return picture

    @app.get(
        "/biases",
        response_model=list[BiasEstimate],
        summary="Each radar's estimated systematic errors",
        description="Range, azimuth and elevation biases from the joint solve over every pair "
        "(absolute against a reference source, else relative between the radars), with the pairs "
        "used and the data time of the solve.",
        responses=_example([EXAMPLES["BiasEstimate"]]),
    )
    def biases(node: NodeDep) -> list[dict[str, Any]]:
        return node.snapshot.biases()

    @app.get(
        "/metrics",
        response_class=Response,
        summary="Prometheus metrics (text exposition)",
        description="Counters and gauges computed at scrape time from the same state as /status "
        "(docs/operations/metrics.md lists them).",
        responses={200: {"content": {CONTENT_TYPE_LATEST: {"example": "topofusion_ready 1.0\n"}}}},
    )
    def metrics(request: Request, node: NodeDep) -> Response:
        return Response(generate_latest(request.app.state.registry), media_type=CONTENT_TYPE_LATEST)

    # The operator picture (contract §4.5): its page, its live feed, its script and styles.
    feed = add_picture(app, limits)
    app.mount(PICTURE_ASSETS, StaticFiles(packages=[("service.api", "static")]), name="static")
    if api_token:
        # around the router: every request meets it before any route, mount or exception handler
        app.add_middleware(BearerTokenMiddleware, token=api_token)
        _document_bearer(app)
    # outermost: a request beyond the bound costs nothing more than its 503
    app.add_middleware(RequestLimitMiddleware, max_requests=limits.max_requests)
    return app
