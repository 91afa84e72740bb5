"""The README's first walk, as written: ``make demo`` (``topofusion demo``, what the Makefile
runs) and, "meanwhile, in another terminal", its block of ``curl`` commands.

Free ports instead of 8000 (HTTP) and the demo's Zenoh port; the browser line (``xdg-open``)
is left out.  Each command must exit 0 and say what the README promises: the status with both
radars, radar A's confirmed tracks, the pairs, the biases.
"""

from __future__ import annotations

import json
import re
import signal
import subprocess
import time
from pathlib import Path

import httpx

from tests.doc_commands import ROOT, TOPOFUSION, code_block, commands, environment, started
from tests.support import free_port

README = ROOT / "README.md"


def _makefile_demo() -> list[str]:
    """The command ``make demo`` runs, with the venv's ``topofusion``."""
    text = (ROOT / "Makefile").read_text()
    line = re.search(r"^demo:.*\n\t(.+)$", text, flags=re.MULTILINE)
    assert line is not None, "the Makefile has no demo target"
    argv = line.group(1).split()
    assert argv[0].endswith("/topofusion") and argv[1] == "demo", argv
    return [TOPOFUSION, *argv[1:]]


def test_the_readme_demo_and_its_curl_block_run_as_written(tmp_path: Path) -> None:
    http = free_port()
    argv = [*_makefile_demo(), "--listen", f"tcp/127.0.0.1:{free_port()}", "--http-port", str(http)]
    block = code_block(README, "Meanwhile, in another terminal:", language="bash")
    lines = [c for c in commands(block) if not c.startswith("xdg-open")]
    assert len(lines) == 4 and all(c.startswith("curl") for c in lines), lines
    with started([*argv, "--speed", "8"], cwd=tmp_path) as demo:
        url = f"http://127.0.0.1:{http}"
        deadline = time.monotonic() + 90
        while time.monotonic() < deadline:
            assert demo.popen.poll() is None, demo.output()
            try:
                status = httpx.get(url + "/status", timeout=2).json()
                if status["pairs_confirmed"] >= 5:
                    break
            except httpx.HTTPError:
                pass
            time.sleep(0.5)
        else:
            raise AssertionError(f"no pairs within 90 s:\n{demo.output()[-2000:]}")
        outputs = []
        for line in lines:
            shell_line = line.replace("localhost:8000", f"127.0.0.1:{http}")
            run = subprocess.run(
                ["bash", "-c", shell_line], capture_output=True, text=True, timeout=30, env=environment()
            )
            assert run.returncode == 0, (line, run.stderr)
            outputs.append(run.stdout)
        demo.popen.send_signal(signal.SIGINT)  # Ctrl-C, as the README says
        assert demo.popen.wait(timeout=30) == 0, demo.output()[-2000:]
        time.sleep(0.2)  # (the reader thread takes the last lines)
        # the README's progress line: "batches N  plots N (N/s)  confirmed tracks N  pairs N ..."
        progress = re.compile(
            r"batches [\d,]+\s+plots [\d,]+ \([\d,]+/s\)\s+confirmed tracks \d+\s+"
            r"pairs \d+ confirmed \(\d+ right by simulator truth\)"
        )
        assert progress.search(demo.output()), demo.output()[-2000:]
    status, tracks, pairs, biases = (json.loads(o) for o in outputs)
    assert sorted(r["radar_id"] for r in status["radars"]) == ["A", "B"]
    assert tracks["radar_id"] == "A" and tracks["tracks"]
    assert all(t["status"] == "confirmed" for t in tracks["tracks"])
    assert any(p["status"] == "confirmed" for ps in pairs for p in ps["pairs"])
    assert {b["radar_id"] for b in biases} <= {"A", "B"}
