"""What the HTTP handlers share: the running node, as a FastAPI dependency."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, HTTPException, Request

from service.transport.node import ServiceNode


def get_node(request: Request) -> ServiceNode:
    """The node the lifespan started; 503 until it has (contract §2)."""
    node: ServiceNode | None = getattr(request.app.state, "node", None)
    if node is None:
        raise HTTPException(status_code=503, detail="service starting")
    return node


NodeDep = Annotated[ServiceNode, Depends(get_node)]
