"""The HTTP side port (docs/contract.md §2).  The lifespan owns the Zenoh node and its worker."""

from __future__ import annotations

from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from typing import Annotated, Any, Literal

from fastapi import Depends, FastAPI, HTTPException, Query, Request
from fastapi.responses import JSONResponse, Response
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

from service.api.metrics import registry_for
from service.transport.node import ServiceNode
from service.wire.models import BiasEstimate, PairSet, RadarInfo, Status, SystemTrackBatch, TrackBatch

StatusFilter = Literal["confirmed", "tentative", "all"]


def get_node(request: Request) -> ServiceNode:
    node: ServiceNode | None = getattr(request.app.state, "node", None)
    if node is None:
        raise HTTPException(status_code=503, detail="service starting")
    return node


NodeDep = Annotated[ServiceNode, Depends(get_node)]


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
    )

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

    return app
