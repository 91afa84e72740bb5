"""Commands of the documentation, run as written: the code blocks, the ``topofusion`` of the
venv, and the processes they start (each stopped by its own pid).

A test may give the commands free ports instead of the fixed ones they name (7447, 8000,
8001), and nothing else; they run in a temporary directory, with ``examples/`` meaning the
repository's.
"""

from __future__ import annotations

import contextlib
import os
import queue
import re
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

from tests.support import free_port

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
TOPOFUSION = str(BIN / "topofusion")
#: The fixed ports the documents name (Zenoh, HTTP), each given a free one in a test.
FIXED_PORTS = ("7447", "8000", "8001")
#: A command started in a test has started (the interpreter, the imports, its router) within
#: this long (s) on a loaded 2-core machine, and a short one has ended within it too; a bound
#: for failures only: the commands take a second or two.
PROCESS_S = 30.0


def code_block(path: Path, heading: str, language: str = "sh", index: int = 0) -> str:
    """The ``index``-th fenced block of ``language`` after the line ``heading`` in ``path``."""
    text = path.read_text()
    start = text.index(f"\n{heading}\n")
    blocks = re.findall(rf"^```{language}\n(.*?)^```", text[start:], flags=re.MULTILINE | re.DOTALL)
    return str(blocks[index])


def commands(block: str) -> list[str]:
    """The block's command lines, continuations joined, comments and blank lines left out."""
    joined = re.sub(r"\\\n\s*", " ", block)
    return [ln.strip() for ln in joined.splitlines() if ln.strip() and not ln.strip().startswith("#")]


def free_ports() -> dict[str, str]:
    return {p: str(free_port()) for p in FIXED_PORTS}


def with_ports(text: str, ports: dict[str, str]) -> str:
    return re.sub(r"(?<=:)(7447|8000|8001)\b", lambda m: ports[m.group(1)], text)


def environment(**extra: str) -> dict[str, str]:
    """The caller's environment without TOPOFUSION_* settings, the venv first on the PATH."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("TOPOFUSION_")}
    env["PATH"] = f"{BIN}{os.pathsep}{env.get('PATH', '')}"
    env["PYTHONUNBUFFERED"] = "1"
    return {**env, **extra}


@dataclass
class Proc:
    """A started process and its output (stdout and stderr together), read as it comes."""

    popen: subprocess.Popen[str]
    lines: queue.Queue[str] = field(default_factory=queue.Queue)
    seen: list[str] = field(default_factory=list)
    #: The thread that reads the output into ``lines`` (:func:`started`).
    reader: threading.Thread | None = None

    def output(self) -> str:
        """What the process has written so far; all of it once the process has ended (the
        reader is given until the pipe's end to put the last lines: read at once, an exit seen
        before the reader's turn gave none)."""
        if self.reader is not None and self.popen.poll() is not None:
            self.reader.join(timeout=5)  # (once: a pipe a child's child still holds waits no more)
            self.reader = None
        while True:
            try:
                self.seen.append(self.lines.get_nowait())
            except queue.Empty:
                return "".join(self.seen)


@contextlib.contextmanager
def started(argv: list[str], cwd: Path, env: dict[str, str] | None = None) -> Iterator[Proc]:
    """``argv`` started; at the end stopped by its pid if it still runs (SIGTERM, then SIGKILL)."""
    popen = subprocess.Popen(
        argv,
        cwd=cwd,
        env=env or environment(),
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,  # its own process group: a script's children go with it
    )
    proc = Proc(popen)
    assert popen.stdout is not None
    stream = popen.stdout
    reader = proc.reader = threading.Thread(target=lambda: [proc.lines.put(x) for x in stream], daemon=True)
    reader.start()
    try:
        yield proc
    finally:
        if popen.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(popen.pid, signal.SIGTERM)  # the group this test started, by its id
            try:
                popen.wait(timeout=15)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(popen.pid, signal.SIGKILL)
                popen.wait(timeout=10)
        reader.join(timeout=5)
        stream.close()
        proc.output()
