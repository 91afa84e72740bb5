"""The operator picture (``/picture``) and the offline ``/docs`` and ``/redoc`` (contract §4.5).

The real service runs in-process on a Zenoh router of its own (loopback, free ports) while a
simulated three-radar stream is published: first its opening minute at once, then the rest at
several times real time, so that the picture keeps changing while a headless Chromium
(tests/browser.py, Debian's package; ``.ci/run`` installs it) looks at it.  The browser tests
are skipped, saying so, only where ``/usr/bin/chromium`` is absent.

Set ``PICTURE_SCREENSHOT=docs/picture.png`` to keep the picture's screenshot (docs/picture.md's).
"""

from __future__ import annotations

import fnmatch
import json
import os
import re
import struct
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from html.parser import HTMLParser
from pathlib import Path
from typing import Any
from urllib.parse import urljoin, urlsplit

import pytest

from service.api.picture import DEFAULT_MAX_ITEMS, STATIC_DIR
from service.transport.session import ZenohOptions, open_session
from tests import browser
from tests.scenario_helpers import scenario_messages
from tests.support import RunningService, free_port, paced_stream, running_service, wait_for, wait_subscribed

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

ROOT = Path(__file__).resolve().parents[1]
#: Data seconds published at once, then the rest of the stream at SPEED times real time (it
#: lasts over a minute of wall time, far longer than the tests need: the fixture stops it).
OPENING_S, DURATION_S, SPEED = 60.0, 400.0, 5.0

needs_chromium = pytest.mark.skipif(
    not browser.available(),
    reason=f"{browser.CHROMIUM} is absent: the browser tests need Debian's chromium "
    "(.ci/run installs it: apt-get install --no-install-recommends chromium)",
)


# -- fixtures --------------------------------------------------------------------------------


@dataclass
class Live:
    service: RunningService
    published: threading.Event  # set once the whole stream is out


@pytest.fixture(scope="module")
def live() -> Iterator[Live]:
    """The service during a three-radar stream (published by a thread this fixture stops)."""
    stream = scenario_messages("three-radar", duration_s=DURATION_S)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(ZenohOptions(mode="router", listen=(endpoint,)))
    try:
        client = open_session(ZenohOptions(mode="client", connect=(endpoint,)))
        try:
            with running_service(endpoint) as svc:
                wait_subscribed(client, "fusion/radar/A/plots")
                wait_subscribed(client, "fusion/radar/A/site")
                with paced_stream(client, stream, OPENING_S, SPEED) as published:
                    yield Live(svc, published)
        finally:
            client.close()
    finally:
        router.close()


@pytest.fixture(scope="module")
def chromium() -> Iterator[browser.Browser]:
    if not browser.available():
        pytest.skip(f"{browser.CHROMIUM} is absent (.ci/run installs Debian's chromium)")
    with browser.Browser(width=1280, height=800) as b:
        yield b


@pytest.fixture
def page(chromium: browser.Browser) -> Iterator[browser.Page]:
    p = chromium.page()
    try:
        yield p
    finally:
        p.close()


def system_ids(svc: RunningService) -> set[str]:
    return {t["system_track_id"] for t in svc.http.get("/system-tracks").json()["system_tracks"]}


def settled(svc: RunningService) -> bool:
    """System tracks and confirmed pairs to show."""
    return len(system_ids(svc)) >= 10 and svc.http.get("/status").json()["pairs_confirmed"] >= 20


def png_size(data: bytes) -> tuple[int, int]:
    assert data[:8] == b"\x89PNG\r\n\x1a\n", "not a PNG"
    width, height = struct.unpack(">II", data[16:24])
    return width, height


# -- references to other hosts ---------------------------------------------------------------


class _Links(HTMLParser):
    """Every URL an HTML page refers to (attributes, inline styles and scripts)."""

    ATTRS = frozenset({"src", "href", "action", "data", "poster", "srcset", "spec-url", "xlink:href"})

    def __init__(self) -> None:
        super().__init__()
        self.urls: list[str] = []
        self._in: str | None = None

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        self._in = tag
        for name, value in attrs:
            if value and name in self.ATTRS:
                self.urls += (
                    [v.strip().split(" ")[0] for v in value.split(",")] if name == "srcset" else [value]
                )
            elif value and name == "style":
                self.urls += re.findall(r"url\(\s*['\"]?([^'\")]+)", value)

    def handle_data(self, data: str) -> None:
        if self._in in ("script", "style"):
            self.urls += re.findall(r"(?:https?:)?//[^\s'\"`)<>]+", data)


def foreign(urls: list[str], base: str) -> list[str]:
    """The URLs (relative ones resolved against ``base``) on a host other than ``base``'s."""
    home = urlsplit(base).netloc
    out = []
    for url in urls:
        full = urlsplit(urljoin(base, url))
        if full.scheme in ("data", "blob", "about", "javascript"):
            continue
        if full.netloc != home:
            out.append(url)
    return out


def page_references(svc: RunningService, path: str) -> list[str]:
    answer = svc.http.get(path)
    assert answer.status_code == 200, path
    assert answer.headers["content-type"].startswith("text/html"), answer.headers["content-type"]
    parser = _Links()
    parser.feed(answer.text)
    return parser.urls


def test_pages_refer_to_nothing_but_the_service(live: Live) -> None:
    svc = live.service
    base = svc.base_url + "/"
    for path in ("/picture", "/docs", "/redoc"):
        urls = page_references(svc, path)
        assert urls, f"{path} loads nothing?"
        assert foreign(urls, svc.base_url + path) == [], path
    # the picture's own script and styles name no URL at all, and are served with their types
    for name, kind in (("picture.js", "javascript"), ("picture.css", "text/css")):
        answer = svc.http.get(f"/static/{name}")
        assert answer.status_code == 200 and kind in answer.headers["content-type"], name
        assert not re.findall(r"https?://|//[a-z0-9-]+\.[a-z]", answer.text, flags=re.IGNORECASE), name
    # and the browser would hold back anything else
    for path in ("/picture", "/docs", "/redoc"):
        policy = svc.http.get(path).headers["content-security-policy"]
        assert "default-src 'self'" in policy and "http" not in policy, (path, policy)
    # the docs' bundles are the service's own files
    docs = svc.http.get("/docs").text
    assert '"validatorUrl": null' in docs  # Swagger UI's badge would ask an outside host
    for url in re.findall(r'(?:src|href)="([^"]+)"', docs + svc.http.get("/redoc").text):
        answer = svc.http.get(urljoin(base, url))
        assert answer.status_code == 200, url
        if url.endswith(".js"):
            assert "javascript" in answer.headers["content-type"], url
        elif url.endswith(".css"):
            assert answer.headers["content-type"].startswith("text/css"), url


# -- the feed --------------------------------------------------------------------------------


def first_event(svc: RunningService, **params: Any) -> dict[str, Any]:
    with svc.http.stream("GET", "/picture/events", params=params) as answer:
        assert answer.status_code == 200
        assert answer.headers["content-type"].startswith("text/event-stream")
        event = None
        for line in answer.iter_lines():
            if line.startswith("event: "):
                event = line.removeprefix("event: ")
            elif line.startswith("data: "):
                assert event == "snapshot"
                body: dict[str, Any] = json.loads(line.removeprefix("data: "))
                return body
    raise AssertionError("the stream ended before its first event")


def test_picture_feed_is_bounded_and_agrees_with_the_api(live: Live) -> None:
    svc = live.service
    wait_for(lambda: settled(svc), timeout=60)
    snap = first_event(svc)
    assert snap["max_items"] == DEFAULT_MAX_ITEMS and snap["status"] == "confirmed"
    assert [s["radar_id"] for s in snap["sites"]] == ["A", "B", "C"]
    assert [r["radar_id"] for r in snap["health"]["radars"]] == ["A", "B", "C"]
    assert set(snap["health"]["correlation"]) >= {"p50_ms", "p99_ms"}
    # confirmed only by default
    assert all(t[-1] == 1 for rows in snap["tracks"].values() for t in rows)
    assert all(t[-1] == 1 for t in snap["system_tracks"])
    assert all(link[-1] == "c" for link in snap["links"])
    assert snap["links"] and all(len(rows) > 0 for rows in snap["tracks"].values())
    # the system tracks are the API's (a second apart at most)
    api = system_ids(svc)
    feed = {t[0] for t in snap["system_tracks"]}
    assert len(feed & api) >= 0.8 * min(len(feed), len(api)), (feed, api)

    small = first_event(svc, max_items=3, status="all")
    assert len(small["system_tracks"]) <= 3 and len(small["links"]) <= 3
    assert sum(len(rows) for rows in small["tracks"].values()) <= 3
    assert small["truncated"]["system_tracks"] > 0 and small["truncated"]["tracks"] > 0
    for bad in ({"max_items": 0}, {"status": "tentative"}, {"interval_s": 0.01}):
        assert svc.http.get("/picture/events", params=bad).status_code == 422, bad


# -- in the browser --------------------------------------------------------------------------


def _dom_ids(dom: str) -> set[str]:
    return set(re.findall(r'<g class="system-track[^"]*" data-track-id="([^"]+)"', dom))


#: What ReDoc 2 asks another host for whatever its options (its sidebar's "API docs by
#: Redocly" logo); the page's Content-Security-Policy keeps it in the browser.
REDOC_LOGO = "https://cdn.redoc.ly/redoc/logo-mini.svg"


def _assert_only_the_service(p: browser.Page, svc: RunningService, held: tuple[str, ...] = ()) -> None:
    """Every request the page let out went to the service; those to other hosts (``held``
    only) were blocked by the page's Content-Security-Policy."""
    ours = (svc.base_url + "/", "blob:" + svc.base_url + "/")
    requests = p.requests()
    assert requests
    assert [(u, why) for u, why in requests if why is None and not u.startswith(ours)] == [], requests
    assert sorted({u for u, why in requests if not u.startswith(ours)}) == sorted(held), requests
    assert all(why == "csp" for u, why in requests if u in held), requests


def _errors(p: browser.Page) -> list[str]:
    """The console's errors but the Content-Security-Policy's reports of what it held back."""
    return [e for e in p.console_errors() if "violates the following Content Security Policy" not in e]


@needs_chromium
def test_picture_renders_the_stream_and_follows_it(live: Live, page: browser.Page) -> None:
    svc = live.service
    wait_for(lambda: settled(svc), timeout=60)
    page.goto(svc.base_url + "/picture")
    page.wait("Number(document.body.dataset.updates) >= 2", what="two snapshots drawn")
    page.wait("document.querySelectorAll('#layer-system [data-track-id]').length >= 10", what="system tracks")

    # the DOM (as --dump-dom prints it) names the system tracks the API has
    dom, api = page.dom(), system_ids(svc)
    ids = _dom_ids(dom)
    assert len(ids & api) >= 0.8 * min(len(ids), len(api)) and len(ids) >= 10, (ids, api)
    for rid in ("A", "B", "C"):
        assert f'<g class="site" data-radar-id="{rid}">' in dom, rid
        assert f'<tr data-radar-id="{rid}">' in dom, rid  # health panel
    counts = page.evaluate(
        "['#layer-tracks circle', '#layer-links line', '#layer-coverage path', '#layer-graticule line']"
        ".map(s => document.querySelectorAll(s).length)"
    )
    assert counts[0] > 0 and counts[1] > 0 and counts[2] == 3 and counts[3] > 4, counts
    rates = page.evaluate(
        "[...document.querySelectorAll('#health tbody tr td:nth-child(2)')].map(e => e.textContent)"
    )
    assert len(rates) == 3, rates

    # it follows the stream: new snapshots, and the picture changes
    assert not live.published.is_set(), "the stream ended before the test could watch it"
    first, updates = page.screenshot(), int(page.evaluate("document.body.dataset.updates"))
    assert png_size(first) == (1280, 800)
    time.sleep(3.0)
    second = page.screenshot()
    assert int(page.evaluate("document.body.dataset.updates")) >= updates + 2
    assert png_size(second) == (1280, 800)
    assert first != second, "the picture did not change in 3 s of a live stream"
    assert page.evaluate("document.getElementById('connection').textContent") == "live"

    # the bias estimates are drawn once the joint solve has some
    wait_for(lambda: svc.http.get("/biases").json(), timeout=60)
    page.wait("document.querySelectorAll('#layer-biases g.bias').length >= 2", what="bias arrows")
    page.wait(
        "document.querySelectorAll('#bias-table tbody tr[data-radar-id]').length >= 2", what="bias table"
    )

    # wheel zooms, drag pans: the sites move on the map
    where = "document.querySelector('#layer-sites path').getAttribute('d')"
    before, scale = page.evaluate(where), page.evaluate("document.getElementById('scale').textContent")
    page.send(
        "Input.dispatchMouseEvent", {"type": "mouseWheel", "x": 400, "y": 400, "deltaX": 0, "deltaY": -400}
    )
    page.wait(f"document.getElementById('scale').textContent !== {json.dumps(scale)}", what="zoom")
    zoomed = page.wait(f"{where} !== {json.dumps(before)} && {where}", what="sites moved by the zoom")
    for kind, x in (("mousePressed", 300), ("mouseMoved", 420), ("mouseReleased", 420)):
        page.send(
            "Input.dispatchMouseEvent",
            {
                "type": kind,
                "x": x,
                "y": 300,
                "button": "left",
                "buttons": 1 if kind != "mouseReleased" else 0,
            },
        )
    page.wait(f"{where} !== {json.dumps(zoomed)}", what="sites moved by the drag")

    assert page.console_errors() == []
    _assert_only_the_service(page, svc)

    keep = os.environ.get("PICTURE_SCREENSHOT")
    if keep:
        page.send("Input.dispatchMouseEvent", {"type": "mouseMoved", "x": 1, "y": 1})
        page.evaluate("document.getElementById('map').dispatchEvent(new MouseEvent('dblclick'))")
        time.sleep(0.5)
        Path(keep).write_bytes(page.screenshot())


@needs_chromium
def test_docs_and_redoc_render_with_no_network(live: Live, page: browser.Page) -> None:
    svc = live.service
    page.goto(svc.base_url + "/docs")
    page.wait("document.querySelectorAll('.opblock').length >= 10", what="Swagger UI's operations")
    paths = page.evaluate("[...document.querySelectorAll('.opblock-summary-path')].map(e => e.textContent)")
    assert "/system-tracks" in [p.replace("\u200b", "") for p in paths], paths
    assert "/picture/events" in [p.replace("\u200b", "") for p in paths], paths
    _assert_only_the_service(page, svc)

    assert page.console_errors() == []

    page.goto(svc.base_url + "/redoc")
    page.wait("document.body.innerText.includes('/system-tracks')", what="ReDoc's operations")
    assert page.evaluate("document.querySelectorAll('[data-section-id]').length") >= 10
    _assert_only_the_service(page, svc, held=(REDOC_LOGO,))
    assert _errors(page) == []


# -- packaging -------------------------------------------------------------------------------


def test_static_files_are_package_data() -> None:
    """Every file of service/api/static/ matches the package data of pyproject.toml (the wheel,
    and so the container image, holds what the pages load; tests/test_packaging.py builds it)."""
    config = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))
    patterns = config["tool"]["setuptools"]["package-data"]["service.api"]
    files = [p.relative_to(STATIC_DIR.parent).as_posix() for p in STATIC_DIR.rglob("*") if p.is_file()]
    assert {"static/picture.html", "static/picture.js", "static/picture.css"} <= set(files)
    # a setuptools pattern's "*" stays within one folder
    missing = [
        f for f in files if not any(fnmatch.fnmatch(f, p) and f.count("/") == p.count("/") for p in patterns)
    ]
    assert missing == [], missing
