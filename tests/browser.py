"""Headless Chromium for the tests, driven over the DevTools protocol on a pipe.

Debian's ``/usr/bin/chromium`` (``.ci/run`` installs it), nothing downloaded: Chromium's
``--remote-debugging-pipe`` takes the DevTools protocol's JSON messages, each ended by a NUL
byte, on its file descriptor 3 and answers on 4, so the standard library drives it.

Why not the command line's ``--dump-dom`` / ``--screenshot``: the picture is fed by
server-sent events, a request that never ends, so ``--virtual-time-budget`` never runs out
(virtual time waits for pending requests) and without it the DOM is dumped at the load event,
before the first event has arrived.  Over the protocol a test keeps one page open, waits for
what it expects, reads the DOM (what ``--dump-dom`` prints), takes screenshots some seconds
apart, and sees every request the page made.

The flags keep Chromium off the network (no background, component, sync or QUIC traffic):
the only requests are the pages' own.  Every browser started here is closed (killed if it
does not close) and its profile directory removed.
"""

from __future__ import annotations

import base64
import contextlib
import json
import os
import queue
import re
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

CHROMIUM = Path("/usr/bin/chromium")
FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--no-default-browser-check",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--disable-extensions",
    "--disable-default-apps",
    "--disable-features=Translate,MediaRouter,OptimizationHints",
    "--metrics-recording-only",
    "--mute-audio",
    "--hide-scrollbars",
)
#: Starts Chromium with the two pipe ends as its descriptors 3 and 4 (``subprocess`` closes
#: every descriptor not passed, and ``preexec_fn`` runs before that and is unsafe with threads).
_SHIM = (
    "import os, sys; os.dup2(int(sys.argv[1]), 3); os.dup2(int(sys.argv[2]), 4); "
    "os.execv(sys.argv[3], sys.argv[3:])"
)


class BrowserError(RuntimeError):
    pass


def available() -> bool:
    return CHROMIUM.is_file() and os.access(CHROMIUM, os.X_OK)


class Browser:
    """One headless Chromium; :meth:`page` opens a tab.  Use as a context manager."""

    def __init__(self, width: int = 1280, height: int = 800, timeout_s: float = 20.0) -> None:
        self.width, self.height, self.timeout_s = width, height, timeout_s
        self._profile = tempfile.mkdtemp(prefix="topofusion-chromium-")
        self._log = open(Path(self._profile) / "chromium.log", "wb")  # noqa: SIM115 (closed in close())
        to_child, self._to_browser = os.pipe()
        self._from_browser, from_child = os.pipe()
        try:
            self.process = subprocess.Popen(
                [
                    sys.executable,
                    "-c",
                    _SHIM,
                    str(to_child),
                    str(from_child),
                    str(CHROMIUM),
                    *FLAGS,
                    f"--user-data-dir={self._profile}",
                    f"--window-size={width},{height}",
                    "--remote-debugging-pipe",
                    "about:blank",
                ],
                stdin=subprocess.DEVNULL,
                stdout=self._log,
                stderr=self._log,
                pass_fds=(to_child, from_child),
            )
        except OSError:
            for fd in (self._to_browser, self._from_browser):
                os.close(fd)
            self._log.close()
            shutil.rmtree(self._profile, ignore_errors=True)
            raise
        finally:
            os.close(to_child)
            os.close(from_child)
        self._next_id = 0
        self._lock = threading.Lock()
        # one message at a time on the pipe: a message over the pipe's atomic size (a routed
        # answer's body) written by two threads at once would interleave
        self._write_lock = threading.Lock()
        self._replies: dict[int, queue.SimpleQueue[dict[str, Any]]] = {}
        self.events: list[dict[str, Any]] = []
        self._reader = threading.Thread(target=self._read, name="chromium-devtools", daemon=True)
        self._reader.start()

    # -- protocol ------------------------------------------------------------------------------
    def _read(self) -> None:
        buffer = b""
        while True:
            try:
                chunk = os.read(self._from_browser, 1 << 16)
            except OSError:
                chunk = b""
            if not chunk:
                break
            buffer += chunk
            *messages, buffer = buffer.split(b"\0")
            for raw in messages:
                message = json.loads(raw)
                if "id" in message:
                    with self._lock:
                        waiting = self._replies.get(message["id"])
                    if waiting is not None:
                        waiting.put(message)
                else:
                    self.events.append(message)
        with self._lock:
            for waiting in self._replies.values():
                waiting.put({"error": {"message": "chromium closed its pipe"}})

    def send(self, method: str, params: dict[str, Any] | None = None, session: str | None = None) -> Any:
        """One command; its result (``BrowserError`` on an error or no answer in time)."""
        reply: queue.SimpleQueue[dict[str, Any]] = queue.SimpleQueue()
        with self._lock:
            self._next_id += 1
            ident = self._next_id
            self._replies[ident] = reply
        message: dict[str, Any] = {"id": ident, "method": method, "params": params or {}}
        if session is not None:
            message["sessionId"] = session
        try:
            data = json.dumps(message).encode() + b"\0"
            with self._write_lock:
                while data:
                    data = data[os.write(self._to_browser, data) :]
            answer = reply.get(timeout=self.timeout_s)
        except (OSError, queue.Empty) as exc:
            raise BrowserError(f"{method}: no answer from chromium ({exc!r}); {self.log_tail()}") from exc
        finally:
            with self._lock:
                self._replies.pop(ident, None)
        if "error" in answer:
            raise BrowserError(f"{method}: {answer['error']}")
        return answer.get("result", {})

    def log_tail(self, chars: int = 2000) -> str:
        self._log.flush()
        try:
            return (Path(self._profile) / "chromium.log").read_text(errors="replace")[-chars:]
        except OSError:
            return ""

    # -- pages ---------------------------------------------------------------------------------
    def page(self) -> Page:
        target = self.send("Target.createTarget", {"url": "about:blank"})["targetId"]
        session = self.send("Target.attachToTarget", {"targetId": target, "flatten": True})["sessionId"]
        return Page(self, target, session)

    def close(self) -> None:
        try:
            if self.process.poll() is None:
                with contextlib.suppress(BrowserError):
                    self.send("Browser.close")
                try:
                    self.process.wait(timeout=5)
                except subprocess.TimeoutExpired:
                    self.process.kill()
                    self.process.wait(timeout=5)
        finally:
            for fd in (self._to_browser, self._from_browser):
                with contextlib.suppress(OSError):
                    os.close(fd)
            self._reader.join(timeout=5)
            self._log.close()
            shutil.rmtree(self._profile, ignore_errors=True)

    def __enter__(self) -> Browser:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class Page:
    """One tab: navigate, evaluate, wait, read the DOM, take screenshots, list requests."""

    def __init__(self, browser: Browser, target: str, session: str) -> None:
        self.browser, self.target, self.session = browser, target, session
        self._routes: list[threading.Thread] = []
        self._closing = threading.Event()
        self.send("Network.enable")
        self.send("Page.enable")
        self.send("Runtime.enable")
        self.send("Log.enable")
        self.send(
            "Emulation.setDeviceMetricsOverride",
            {"width": browser.width, "height": browser.height, "deviceScaleFactor": 1, "mobile": False},
        )

    def send(self, method: str, params: dict[str, Any] | None = None) -> Any:
        return self.browser.send(method, params, self.session)

    def close(self) -> None:
        self._closing.set()
        for thread in self._routes:
            thread.join(timeout=5)
        self.browser.send("Target.closeTarget", {"targetId": self.target})

    def route(
        self, pattern: str, answer: Callable[[str], tuple[int, bytes]], content_type: str = "application/json"
    ) -> None:
        """Answer the page's requests whose URL matches ``pattern`` (DevTools' wildcards ``*``
        and ``?``) with ``answer(url)``: a status and a body of ``content_type``, in place of
        the server's (a route the service does not have yet, or an answer a test wants drawn).
        A thread of its own answers them: the reader thread must not wait for a reply."""
        self.send("Fetch.enable", {"patterns": [{"urlPattern": pattern, "requestStage": "Request"}]})

        def serve() -> None:
            done = 0
            while not self._closing.wait(0.02):
                paused = self._events("Fetch.requestPaused")
                for event in paused[done:]:
                    status, body = answer(event["request"]["url"])
                    with contextlib.suppress(BrowserError):
                        self.send(
                            "Fetch.fulfillRequest",
                            {
                                "requestId": event["requestId"],
                                "responseCode": status,
                                "responseHeaders": [{"name": "Content-Type", "value": content_type}],
                                "body": base64.b64encode(body).decode(),
                            },
                        )
                done = len(paused)

        thread = threading.Thread(target=serve, name="chromium-route", daemon=True)
        thread.start()
        self._routes.append(thread)

    def _events(self, method: str) -> list[dict[str, Any]]:
        return [
            e["params"]
            for e in list(self.browser.events)
            if e.get("sessionId") == self.session and e.get("method") == method
        ]

    def goto(self, url: str) -> None:
        """Navigate and wait for the load event."""
        loads = len(self._events("Page.loadEventFired"))
        answer = self.send("Page.navigate", {"url": url})
        if answer.get("errorText"):
            raise BrowserError(f"navigation to {url} failed: {answer['errorText']}")
        self.wait(lambda: len(self._events("Page.loadEventFired")) > loads, what=f"load of {url}")

    def evaluate(self, expression: str) -> Any:
        answer = self.send("Runtime.evaluate", {"expression": expression, "returnByValue": True})
        if "exceptionDetails" in answer:
            raise BrowserError(f"{expression!r} raised {answer['exceptionDetails']}")
        return answer["result"].get("value")

    def wait(self, predicate: Any, timeout_s: float = 20.0, what: str = "condition") -> Any:
        """Until ``predicate()`` (or the JavaScript ``predicate``, a string) is truthy."""
        deadline = time.monotonic() + timeout_s
        last = None
        while time.monotonic() < deadline:
            last = self.evaluate(predicate) if isinstance(predicate, str) else predicate()
            if last:
                return last
            time.sleep(0.1)
        raise AssertionError(f"{what} not met within {timeout_s} s (last: {last!r})")

    def dom(self) -> str:
        """The document as serialised now (what ``chromium --dump-dom`` prints)."""
        return str(self.evaluate("document.documentElement.outerHTML"))

    def screenshot(self) -> bytes:
        """A PNG of the viewport."""
        return base64.b64decode(self.send("Page.captureScreenshot", {"format": "png"})["data"])

    def requests(self) -> list[tuple[str, str | None]]:
        """Every request the page made (data: URLs left out), in order: its URL, and why the
        browser blocked it (e.g. ``csp``: the page's Content-Security-Policy), None if not."""
        blocked = {e["requestId"]: e.get("blockedReason") for e in self._events("Network.loadingFailed")}
        return [
            (e["request"]["url"], blocked.get(e["requestId"]))
            for e in self._events("Network.requestWillBeSent")
            if not e["request"]["url"].startswith("data:")
        ]

    def requested_urls(self) -> list[str]:
        """The URLs of the requests the browser let out."""
        return [url for url, blocked in self.requests() if blocked is None]

    def console_errors(self, but_urls: str | None = None) -> list[str]:
        """The page's uncaught exceptions and the console's errors, but those about a URL
        matching the regular expression ``but_urls`` (e.g. a 404 the page expects)."""
        errors = [
            str(e["exceptionDetails"].get("exception", {}).get("description") or e["exceptionDetails"])
            for e in self._events("Runtime.exceptionThrown")
        ]
        errors += [
            str(e["entry"].get("text"))
            for e in self._events("Log.entryAdded")
            if e.get("entry", {}).get("level") == "error"
            and not (but_urls and re.search(but_urls, e["entry"].get("url") or ""))
        ]
        return errors
