"""The HTTP bearer token (``TOPOFUSION_API_TOKEN``, docs/contract.md §4.6), over real HTTP.

Two services run in-process, clients of one Zenoh router on a free loopback port, each with
uvicorn on a free port: one with a token, one without.  A short two-radar stream gives them
tracks, so that every route has something to answer.  The routes asked are the app's own
(``app.routes``, mounts included): an endpoint added later is covered without touching this file.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import re
import secrets
import socket
import threading
from collections.abc import Iterator
from dataclasses import dataclass, field
from functools import partial
from html.parser import HTMLParser
from typing import Any
from urllib.parse import unquote, urljoin

import httpx
import pytest
import uvicorn
from fastapi import FastAPI
from starlette.routing import Mount, Route
from starlette.staticfiles import StaticFiles

from service.api.app import TOKEN_COOKIE, create_app
from service.api.picture import CACHE_S
from service.engine import EngineConfig
from service.transport.node import ServiceNode
from service.transport.session import ZenohOptions, open_session
from tests.scenario_helpers import scenario_messages
from tests.support import free_port, put_json, wait_for, wait_subscribed

#: A fresh token per run, of the kind an operator generates.
TOKEN = secrets.token_urlsafe(24)
OPEN = ("/healthz", "/readyz")
#: The one kind of path parameter the app has; a route with another makes the test say so.
PATH_VALUES = {"radar_id": "A"}


@dataclass
class Served:
    app: FastAPI
    base_url: str
    node: dict[str, ServiceNode] = field(default_factory=dict)

    def client(self, **kw: Any) -> httpx.Client:
        return httpx.Client(base_url=self.base_url, timeout=10.0, follow_redirects=False, **kw)


class _Captured(logging.Handler):
    def __init__(self) -> None:
        super().__init__(level=logging.DEBUG)
        self.lines: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        # the tests' own HTTP client logs the addresses it asks, /picture?token=... among them
        if not record.name.startswith(("httpx", "httpcore")):
            self.lines.append(self.format(record))


@contextlib.contextmanager
def _serve(router: str, api_token: str | None) -> Iterator[Served]:
    """The service as ``topofusion run`` serves it (no access log), on a free port."""
    node: dict[str, ServiceNode] = {}

    def factory() -> ServiceNode:
        node["node"] = ServiceNode(EngineConfig(), ZenohOptions(mode="client", connect=(router,)))
        return node["node"]

    app = create_app(factory, api_token=api_token)
    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    port = sock.getsockname()[1]
    config = uvicorn.Config(app, log_level="debug", access_log=False, lifespan="on", log_config=None)
    server = uvicorn.Server(config)
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    served = Served(app, f"http://127.0.0.1:{port}", node)
    try:
        with served.client() as http:  # /readyz needs no token
            wait_for(lambda: server.started, timeout=15)
            wait_for(lambda: http.get("/readyz").status_code == 200, timeout=15)
        yield served
    finally:
        server.should_exit = True
        thread.join(timeout=10)
        sock.close()
        assert not thread.is_alive(), "uvicorn did not stop"


@dataclass
class Services:
    guarded: Served
    open: Served
    logs: _Captured


@pytest.fixture(scope="module")
def services() -> Iterator[Services]:
    logs = _Captured()
    root = logging.getLogger()
    previous = root.level
    root.addHandler(logs)
    root.setLevel(logging.DEBUG)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(ZenohOptions(mode="router", listen=(endpoint,)))
    try:
        client = open_session(ZenohOptions(mode="client", connect=(endpoint,)))
        try:
            with _serve(endpoint, TOKEN) as guarded, _serve(endpoint, None) as plain:
                wait_subscribed(client, "fusion/radar/A/plots")
                wait_subscribed(client, "fusion/radar/A/site")
                for key, payload in scenario_messages("two-radar", duration_s=20.0):
                    put_json(client, key, payload)
                for svc, headers in ((guarded, _bearer(TOKEN)), (plain, {})):
                    with svc.client(headers=headers) as http:
                        wait_for(partial(_answers, http, "/radars/A/tracks"), timeout=30)
                yield Services(guarded, plain, logs)
        finally:
            client.close()
    finally:
        router.close()
        root.removeHandler(logs)
        root.setLevel(previous)


def _answers(http: httpx.Client, url: str) -> bool:
    return http.get(url).status_code == 200


def _bearer(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


def _a_file(static: StaticFiles) -> str:
    """A file a static mount serves (its first, by name)."""
    for directory in static.all_directories:
        for top, _, files in sorted(os.walk(directory)):
            if files:
                return os.path.relpath(os.path.join(top, sorted(files)[0]), directory).replace(os.sep, "/")
    raise AssertionError("a static mount without files")


def every_address(app: FastAPI) -> list[str]:
    """One address per route of the app, and a file of each mount."""
    out = []
    for route in app.routes:
        if isinstance(route, Mount):
            assert isinstance(route.app, StaticFiles), f"mount {route.path}: teach this test what it serves"
            out.append(f"{route.path}/{_a_file(route.app)}")
        else:
            assert isinstance(route, Route), route
            assert route.methods is not None and route.methods <= {"GET", "HEAD"}, (
                f"{route.path} takes {route.methods}: teach this test what to send"
            )
            names = set(re.findall(r"{(\w+)(?::\w+)?}", route.path))
            assert names <= set(PATH_VALUES), f"{route.path}: teach this test a value for {names}"
            out.append(re.sub(r"{(\w+)(?::\w+)?}", lambda m: PATH_VALUES[m[1]], route.path))
    assert {"/status", "/picture/events", "/openapi.json", "/docs"} <= set(out), out
    return out


def _status(http: httpx.Client, url: str, **kw: Any) -> httpx.Response:
    """The response's status and headers, its body read unless it streams (``/picture/events``)."""
    with http.stream("GET", url, **kw) as response:
        if not response.headers.get("content-type", "").startswith("text/event-stream"):
            response.read()
        return response


def _refused(response: httpx.Response) -> bool:
    return (
        response.status_code == 401
        and response.headers["www-authenticate"].startswith("Bearer")
        and isinstance(response.json()["detail"], str)
    )


def snapshots(http: httpx.Client, url: str = "/picture/events", count: int = 1) -> list[dict[str, Any]]:
    """The first ``count`` snapshots of the picture's feed."""
    out: list[dict[str, Any]] = []
    with http.stream("GET", url) as response:
        assert response.status_code == 200, response.status_code
        assert response.headers["content-type"].startswith("text/event-stream")
        for line in response.iter_lines():
            if line.startswith("data: "):
                out.append(json.loads(line[len("data: ") :]))
                if len(out) == count:
                    return out
    raise AssertionError(f"the feed ended after {len(out)} snapshots")


# -- the token on every route ----------------------------------------------------------------


def test_every_route_answers_with_the_token(services: Services) -> None:
    with services.guarded.client(headers=_bearer(TOKEN)) as http:
        for url in every_address(services.guarded.app):
            assert _status(http, url).status_code == 200, url
        # the scheme's name is case-insensitive (RFC 7235)
        assert http.get("/status", headers={"Authorization": f"bearer {TOKEN}"}).status_code == 200
        assert http.get("/no-such-endpoint").status_code == 404  # let in, then routed


def test_every_route_but_the_probes_refuses_without_the_token(services: Services) -> None:
    with services.guarded.client() as http:
        for url in every_address(services.guarded.app):
            response = _status(http, url)
            if url in OPEN:
                assert response.status_code == 200, url
            else:
                assert _refused(response), (url, response.status_code, response.headers)
        # refused before routing: an unknown address says nothing of what exists
        assert _refused(http.get("/no-such-endpoint"))
        assert _refused(http.get("/static/no-such-file.js"))


def test_the_probes_answer_head_as_get_without_a_body(services: Services) -> None:
    """A load balancer or ``curl -I`` asks the probes with HEAD: the status of GET, no body
    (it was 405), and no token needed."""
    with services.guarded.client() as http:
        for url in OPEN:
            got, head = http.get(url), http.head(url)
            assert (head.status_code, head.content) == (got.status_code, b""), url
            assert head.headers["content-type"] == got.headers["content-type"]


@pytest.mark.parametrize(
    "authorization",
    [
        pytest.param(f"Bearer {TOKEN[:-1]}{'A' if TOKEN[-1] != 'A' else 'B'}", id="same-length"),
        pytest.param(f"Bearer {TOKEN}x", id="longer"),
        pytest.param(f"Bearer {TOKEN[:-1]}", id="shorter"),
        pytest.param("Bearer", id="empty"),
        pytest.param(f"Basic {TOKEN}", id="other-scheme"),
        pytest.param(TOKEN, id="no-scheme"),
    ],
)
def test_a_wrong_token_is_refused(services: Services, authorization: str) -> None:
    with services.guarded.client(headers={"Authorization": authorization}) as http:
        for url in ("/status", "/metrics", "/picture", "/static/picture.js", "/openapi.json", "/docs"):
            assert _refused(_status(http, url)), url
        for url in OPEN:  # a probe with a stale header still works
            assert http.get(url).status_code == 200


def test_the_token_in_an_address_opens_only_the_picture(services: Services) -> None:
    with services.guarded.client() as http:
        assert _refused(http.get("/status", params={"token": TOKEN}))
        assert _refused(http.get("/picture/events", params={"token": TOKEN}))


def test_the_openapi_document_says_which_operations_need_the_token(services: Services) -> None:
    with services.guarded.client(headers=_bearer(TOKEN)) as http:
        doc = http.get("/openapi.json").json()
    assert doc["components"]["securitySchemes"]["bearer"] == {"type": "http", "scheme": "bearer"}
    for path, operations in doc["paths"].items():
        for operation in operations.values():
            if path in OPEN:
                assert "security" not in operation, path
            else:
                assert operation["security"] == [{"bearer": []}] and "401" in operation["responses"], path


# -- the picture in a browser: the token once in the address, then a cookie ------------------


class _Assets(HTMLParser):
    def __init__(self) -> None:
        super().__init__()
        self.urls: list[str] = []

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        for name, value in attrs:
            if name in ("src", "href") and value and not value.startswith("data:"):
                self.urls.append(value)


def test_the_picture_trades_the_token_for_a_cookie(services: Services) -> None:
    svc = services.guarded
    with svc.client() as browser:
        response = browser.get("/picture", params={"status": "all", "token": TOKEN})
        assert response.status_code == 303
        assert response.headers["location"] == "/picture?status=all"  # the token leaves the address
        assert TOKEN not in response.headers["location"]
        [set_cookie] = response.headers.get_list("set-cookie")
        name, _, rest = set_cookie.partition("=")
        value, *attributes = [a.strip() for a in rest.split(";")]
        assert name == TOKEN_COOKIE and unquote(value) == TOKEN
        flags = {a.split("=")[0].lower(): a.partition("=")[2] for a in attributes}
        assert "httponly" in flags and flags["samesite"].lower() == "strict" and flags["path"] == "/"
        assert "secure" not in flags  # plain HTTP here: a secure cookie would never come back

        # the browser follows the redirect with the cookie only, and the page's own requests too
        page = browser.get(response.headers["location"])
        assert page.status_code == 200 and "text/html" in page.headers["content-type"]
        assert "Authorization" not in page.request.headers
        parser = _Assets()
        parser.feed(page.text)
        assert parser.urls, "the page loads its script and styles"
        for url in parser.urls:
            assert browser.get(urljoin(str(page.url), url)).status_code == 200, url
        [snapshot] = snapshots(browser, urljoin(str(page.url), "picture/events"))
        assert {s["radar_id"] for s in snapshot["sites"]} == {"A", "B"}
        # the cookie opens the rest of the API in that browser (the docs, for one)
        assert browser.get("/docs").status_code == 200
        assert browser.get("/status").json()["prefix"] == "fusion"


def test_the_picture_refuses_a_wrong_token_or_cookie(services: Services) -> None:
    with services.guarded.client() as browser:
        response = browser.get("/picture", params={"token": TOKEN + "x"})
        assert _refused(response) and "set-cookie" not in response.headers
        assert _refused(browser.get("/picture", params=[("token", TOKEN), ("token", "other")]))
    with services.guarded.client(headers={"Cookie": f"{TOKEN_COOKIE}={TOKEN[:-1]}"}) as browser:
        assert _refused(browser.get("/picture"))
        assert _refused(browser.get("/picture/events"))


def test_a_cookie_from_the_exchange_is_the_token(services: Services) -> None:
    """Also the picture's cookie is compared with the token, not trusted for being there."""
    with services.guarded.client(headers={"Cookie": f"{TOKEN_COOKIE}={TOKEN}"}) as browser:
        assert browser.get("/picture").status_code == 200
        # the feed goes on streaming through the check: fresh snapshots, one per interval (the
        # interval longer than the time a snapshot is shared, service.api.picture.CACHE_S)
        feed = snapshots(browser, f"/picture/events?interval_s={CACHE_S + 0.1}", count=3)
        assert [s["status"] for s in feed] == ["confirmed"] * 3
        assert feed[0]["wall_s"] < feed[1]["wall_s"] < feed[2]["wall_s"]


# -- without a token: as before --------------------------------------------------------------


def test_without_a_token_everything_is_open(services: Services) -> None:
    with services.open.client() as http:
        for url in every_address(services.open.app):
            assert _status(http, url).status_code == 200, url
        # the token's address is only the page's: nothing to trade without a token
        assert http.get("/picture", params={"token": "anything"}).status_code == 200
        doc = http.get("/openapi.json").json()
        assert "securitySchemes" not in doc.get("components", {})
    # an empty token (an unset variable compose passes through as "") is no token
    app = create_app(lambda: None, api_token="")  # type: ignore[arg-type, return-value]
    assert asyncio.run(_in_process(app, "/openapi.json")) == 200


async def _in_process(app: FastAPI, url: str) -> int:
    """A request straight to the app (no server, no lifespan: no node needed)."""
    transport = httpx.ASGITransport(app=app)
    async with httpx.AsyncClient(transport=transport, base_url="http://app") as http:
        return (await http.get(url)).status_code


def test_the_token_is_never_logged(services: Services) -> None:
    """Every log line of both services so far, at debug level (the module's tests ran first)."""
    text = "\n".join(services.logs.lines)
    assert text, "nothing was logged: the capture is broken"
    assert TOKEN not in text
