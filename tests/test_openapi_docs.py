"""`/docs` that teach: every route of the contract's HTTP port has a summary of its own, a
description, and an example answer (the contract's own, as in schemas/examples)."""

from __future__ import annotations

from typing import Any

import pytest

from service.api.app import create_app
from service.engine import EngineConfig
from service.transport.node import ServiceNode
from service.transport.session import ZenohOptions

#: The contract's routes (docs/contract.md §2, §4.4): the picture's own page is documented in
#: service/api/picture.py.
ROUTES = (
    "/healthz",
    "/readyz",
    "/status",
    "/radars",
    "/radars/{radar_id}/tracks",
    "/pairs",
    "/system-tracks",
    "/biases",
    "/metrics",
)


@pytest.fixture(scope="module")
def openapi() -> dict[str, Any]:
    # (the node is built at start-up only; the schema needs none)
    app = create_app(lambda: ServiceNode(EngineConfig(), ZenohOptions(mode="peer")))
    return app.openapi()


@pytest.mark.parametrize("path", ROUTES)
def test_every_route_has_a_summary_a_description_and_an_example(openapi: dict[str, Any], path: str) -> None:
    op = openapi["paths"][path]["get"]
    generated = path.strip("/").split("/")[-1].replace("-", " ").title()
    assert op.get("summary") and op["summary"] != generated, op.get("summary")
    assert len(op.get("description", "")) > 40
    content = op["responses"]["200"]["content"]
    assert any("example" in media for media in content.values()), content


def test_the_examples_are_valid_answers(openapi: dict[str, Any]) -> None:
    """Each JSON example has the fields its response schema requires."""
    schemas = openapi["components"]["schemas"]
    checked = 0
    for path in ROUTES:
        op = openapi["paths"][path]["get"]
        media = op["responses"]["200"]["content"].get("application/json")
        schema = media.get("schema") if media else None
        if not schema:
            continue
        example = media["example"]
        if schema.get("type") == "array":
            assert isinstance(example, list) and example
            schema, example = schema["items"], example[0]
        if "$ref" not in schema:
            continue  # (the probes: a plain object)
        name = schema["$ref"].rsplit("/", 1)[-1]
        assert set(schemas[name].get("required", [])) <= set(example), (path, name)
        checked += 1
    assert checked >= 6
