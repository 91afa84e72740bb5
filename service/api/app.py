"""The HTTP side port (docs/contract.md §2).  The lifespan owns the Zenoh node and its worker."""

from __future__ import annotations

from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from typing import Annotated, Any, Literal

from fastapi import Depends, FastAPI, HTTPException, Query, Request
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html, get_swagger_ui_oauth2_redirect_html
from fastapi.responses import HTMLResponse, JSONResponse, Response
from fastapi.staticfiles import StaticFiles
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

from service.api.metrics import registry_for
from service.api.picture import add_picture
from service.transport.node import ServiceNode
from service.wire.models import BiasEstimate, PairSet, RadarInfo, Status, SystemTrackBatch, TrackBatch

StatusFilter = Literal["confirmed", "tentative", "all"]


def get_node(request: Request) -> ServiceNode:
    node: ServiceNode | None = getattr(request.app.state, "node", None)
    if node is None:
        raise HTTPException(status_code=503, detail="service starting")
    return node


NodeDep = Annotated[ServiceNode, Depends(get_node)]

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


def create_app(
    node_factory: Callable[[], ServiceNode],
    on_started: Callable[[ServiceNode], None] | None = None,
    on_stopping: Callable[[ServiceNode], None] | None = None,
) -> FastAPI:
    """An app whose lifespan starts ``node_factory()`` and stops it on shutdown.

    ``on_started`` / ``on_stopping`` run right after the node starts and right before it
    stops (the demo starts and stops its simulator there).
    """

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

    @app.get("/healthz")
    def healthz() -> dict[str, str]:
        return {"status": "ok"}

    @app.get("/readyz", responses={503: {"description": "not ready"}})
    def readyz(request: Request) -> JSONResponse:
        node: ServiceNode | None = getattr(request.app.state, "node", None)
        if node is None or not node.ready:
            reason = "starting" if node is None else (node.not_ready_reason or "worker not running")
            return JSONResponse({"status": "not ready", "reason": reason}, status_code=503)
        return JSONResponse({"status": "ready"})

    @app.get("/status", response_model=Status)
    def status(node: NodeDep) -> dict[str, Any]:
        return node.status()

    @app.get("/radars", response_model=list[RadarInfo])
    def radars(node: NodeDep) -> list[dict[str, Any]]:
        return node.radars()

    @app.get(
        "/radars/{radar_id}/tracks",
        response_model=TrackBatch,
        responses={404: {"description": "unknown radar"}},
    )
    def tracks(node: NodeDep, radar_id: str, status: StatusFilter = "confirmed") -> dict[str, Any]:
        batch = node.snapshot.track_batch(radar_id, status)
        if batch is None:
            raise HTTPException(status_code=404, detail=f"unknown radar {radar_id!r}")
        return batch

    @app.get("/pairs", response_model=list[PairSet])
    def pairs(
        node: NodeDep,
        radar_a: Annotated[str | None, Query()] = None,
        radar_b: Annotated[str | None, Query()] = None,
        status: StatusFilter = "confirmed",
    ) -> list[dict[str, Any]]:
        return node.pair_sets(radar_a, radar_b, status)

    @app.get("/system-tracks", response_model=SystemTrackBatch)
    def system_tracks(node: NodeDep, status: StatusFilter = "confirmed") -> dict[str, Any]:
        return node.snapshot.system_tracks(status)

    @app.get("/biases", response_model=list[BiasEstimate])
    def biases(node: NodeDep) -> list[dict[str, Any]]:
        return node.snapshot.biases()

    @app.get("/metrics", response_class=Response)
    def metrics(request: Request, node: NodeDep) -> Response:
        return Response(generate_latest(request.app.state.registry), media_type=CONTENT_TYPE_LATEST)

    # The operator picture (contract §4.5): its page, its live feed, its script and styles.
    add_picture(app)
    app.mount(PICTURE_ASSETS, StaticFiles(packages=[("service.api", "static")]), name="static")
    return app
