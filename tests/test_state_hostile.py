"""``--state-dir``: whatever lies at ``DIR/state.bin`` when the service starts (service/state).

The file is read at every start, before any input: something that is not a state file, a file
too large, a decompression bomb, a whole file (its checksum fixed) with values that cannot be
believed, a directory that cannot be written, the last track-id epoch.  Each must cost bounded
time and memory, be refused with one line saying what and which field, and leave the service
running as after a fresh start (or, read-only, as after a restore); what an operator checks is
checked: the line, the service's answers, the file left behind.

The real keeper on real files; where it matters (a FIFO, a full disk, the last epoch) the real
service process, as tests/test_state_restart.py runs it.  Memory is measured in a process of
its own (its peak resident set while it loads one file).
"""

from __future__ import annotations

import hashlib
import io
import json
import logging
import math
import os
import shutil
import signal
import stat
import struct
import subprocess
import sys
import threading
import time
import zlib
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

from service.engine import Engine, EngineConfig
from service.state import StateKeeper, keeper
from service.state.content import MAX_KEPT_SEQ, check
from service.state.fileformat import (
    MAGIC,
    MAX_EPOCH,
    MAX_FILE_BYTES,
    MAX_INFLATED_BYTES,
    VERSION,
    Header,
    decode,
    encode,
    read_file,
)
from service.state.keeper import EpochsExhaustedError
from tests.scenario_helpers import scenario_messages
from tests.support import free_port, wait_for
from tests.test_cli_process import TOPOFUSION, _http_ready
from tests.test_state import _errors, _feed, _radar, _split, _track_ids

STATE = "state.bin"
REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(autouse=True)
def _info(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO, logger="service.state")


@pytest.fixture(scope="module")
def stream() -> list[tuple[str, bytes]]:
    return scenario_messages("two-radar", duration_s=120.0)


@pytest.fixture(scope="module")
def written(stream: list[tuple[str, bytes]], tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A state file as a first run left it at a graceful stop after 90 s (sites, both radars'
    clocks, a registration memory, the joint biases)."""
    directory = tmp_path_factory.mktemp("written")
    engine = Engine(EngineConfig())
    keeper_ = StateKeeper(directory, "fusion", "1/1")
    keeper_.restore(engine)
    _feed(engine, _split(stream)[0], keeper_)
    keeper_.save(engine)
    return directory / STATE


def _restore(directory: Path, timeout: float = 20.0) -> tuple[StateKeeper, Engine]:
    """A fresh engine restored from ``directory``, on a thread: a start that blocks (a FIFO's
    open) fails the test after ``timeout`` instead of hanging it."""
    engine = Engine(EngineConfig())
    keeper_ = StateKeeper(directory, "fusion", "1/1")
    failure: list[BaseException] = []

    def run() -> None:
        try:
            keeper_.restore(engine)
        except BaseException as exc:
            failure.append(exc)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    thread.join(timeout)
    assert not thread.is_alive(), f"the start blocked for {timeout} s"
    if failure:
        raise failure[0]
    return keeper_, engine


def _line(caplog: pytest.LogCaptureFixture) -> logging.LogRecord:
    """The one line the start logged."""
    [record] = [r for r in caplog.records if r.name == "service.state.keeper"]
    return record


def _clean(engine: Engine) -> bool:
    """Nothing of a state in ``engine``: as after a start without a state directory."""
    snap = engine.snapshot()
    return snap.sites == {} and snap.biases() == [] and not engine.sequencer.sources


def _file(header: Header, body: bytes) -> bytes:
    """A state file of ``header`` and ``body`` with a correct checksum (as anyone can write)."""
    head = json.dumps(asdict(header)).encode()
    content = struct.pack(">16sII", MAGIC, VERSION, len(head)) + head + body
    return content + hashlib.sha256(content).digest()


def _crafted(written: Path, edit: Callable[[Header, dict[str, Any]], Header | None]) -> bytes:
    """``written`` with its header and tree changed by ``edit``, checksum fixed."""
    header, tree = decode(written.read_bytes(), "fusion", "1/1")
    return encode(edit(header, tree) or header, tree)


# -- what is not a regular file ---------------------------------------------------------------


def _symlink_to_dev_zero(path: Path) -> None:
    path.symlink_to("/dev/zero")


def _fifo(path: Path) -> None:
    os.mkfifo(path)


def _symlink_to_fifo(path: Path) -> None:
    os.mkfifo(path.with_name("pipe"))
    path.symlink_to(path.with_name("pipe"))


def _directory(path: Path) -> None:
    path.mkdir()
    (path / "inside").write_bytes(b"x")


@pytest.mark.parametrize(
    ("make", "what"),
    [
        (_symlink_to_dev_zero, "a symbolic link to a character device"),
        (_fifo, "a FIFO"),
        (_symlink_to_fifo, "a symbolic link to a FIFO"),
        (_directory, "a directory"),
    ],
    ids=["symlink-to-dev-zero", "fifo", "symlink-to-fifo", "directory"],
)
def test_what_is_not_a_regular_file_is_refused_without_being_read(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, make: Callable[[Path], None], what: str
) -> None:
    make(tmp_path / STATE)
    kind = stat.S_IFMT(os.lstat(tmp_path / STATE).st_mode)
    t0 = time.monotonic()
    keeper_, engine = _restore(tmp_path)
    assert time.monotonic() - t0 < 5.0
    record = _line(caplog)
    assert record.levelno == logging.WARNING
    assert record.getMessage() == (
        f"state {tmp_path / STATE} refused (not a regular file but {what}): renamed to "
        "state.bin.refused, starting clean; track-id epoch 0"
    )
    assert _clean(engine) and keeper_.epoch == 0
    # it is kept aside as it was (a link stays a link); the clean state is the file now
    assert stat.S_IFMT(os.lstat(tmp_path / "state.bin.refused").st_mode) == kind
    assert decode(read_file(tmp_path / STATE), "fusion", "1/1")[0].epoch == 0


def test_a_file_beyond_the_size_bound_is_refused_before_it_is_read(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    with open(tmp_path / STATE, "wb") as f:  # sparse: no disk, the size is what counts
        f.truncate(MAX_FILE_BYTES + 1)
    keeper_, engine = _restore(tmp_path)
    assert (
        f"refused ({MAX_FILE_BYTES + 1} bytes, more than the {MAX_FILE_BYTES} a state file may have)"
        in _line(caplog).getMessage()
    )
    assert _clean(engine) and keeper_.epoch == 0


# -- decompression bombs ----------------------------------------------------------------------

#: What the bombs inflate to: far beyond what either declares, and it would take that much
#: memory if inflated (a naive reader's fate); zeros, so that it deflates to a few MB.
BOMB_BYTES = 512 << 20


def _npy(array: np.ndarray) -> bytes:
    out = io.BytesIO()
    np.lib.format.write_array(out, array, allow_pickle=False)
    return out.getvalue()


def _npy_header(shape: tuple[int, ...]) -> bytes:
    """The header of a float64 ``.npy`` array of ``shape`` (and no data)."""
    out = io.BytesIO()
    np.lib.format.write_array_header_1_0(out, {"descr": "<f8", "fortran_order": False, "shape": shape})
    return out.getvalue()


def _archive(members: list[tuple[str, bytes, int, int, int]]) -> bytes:
    """A zip archive as numpy's ``savez`` lays it out: ``(name, bytes as stored, method (0
    stored, 8 deflated), CRC, declared inflated size)`` per member."""
    out, central = bytearray(), bytearray()
    for name, data, method, crc, size in members:
        offset, raw = len(out), name.encode()
        out += struct.pack(
            "<4s2B4HL2L2H", b"PK\x03\x04", 20, 0, 0, method, 0, 0, crc, len(data), size, len(raw), 0
        )
        out += raw + data
        central += struct.pack(
            "<4s4B4HL2L5H2L",
            b"PK\x01\x02",
            20,
            3,
            20,
            0,
            0,
            method,
            0,
            0,
            crc,
            len(data),
            size,
            len(raw),
            0,
            0,
            0,
            0,
            0,
            offset,
        )
        central += raw
    n = len(members)
    return bytes(
        out + central + struct.pack("<4s4H2LH", b"PK\x05\x06", 0, 0, n, n, len(central), len(out), 0)
    )


@pytest.fixture(scope="module")
def bomb() -> bytes:
    """An array member of :data:`BOMB_BYTES` (its header says so), deflated: about 2 MB."""
    head = _npy_header((BOMB_BYTES // 8,))
    deflater = zlib.compressobj(1, zlib.DEFLATED, -zlib.MAX_WBITS)
    zeros = bytes(16 << 20)
    parts = [deflater.compress(head)] + [deflater.compress(zeros) for _ in range(BOMB_BYTES // len(zeros))]
    return b"".join([*parts, deflater.flush()])


def _bomb_file(bomb: bytes, declared: int) -> bytes:
    """A whole state file (checksum right) whose one array is ``bomb``, declared ``declared``."""
    tree = _npy(np.frombuffer(b'{"x":{"__array__":"a0"}}', dtype=np.uint8))
    body = _archive([("tree.npy", tree, 0, zlib.crc32(tree), len(tree)), ("a0.npy", bomb, 8, 0, declared)])
    return _file(Header("fusion", "1/1", 4, None, time.time()), body)


def _lying_header_file() -> bytes:
    """A stored array whose header declares 2 GiB over 800 bytes of data."""
    data = _npy_header((1 << 28,)) + bytes(800)
    tree = _npy(np.frombuffer(b'{"x":{"__array__":"a0"}}', dtype=np.uint8))
    body = _archive(
        [
            ("tree.npy", tree, 0, zlib.crc32(tree), len(tree)),
            ("a0.npy", data, 0, zlib.crc32(data), len(data)),
        ]
    )
    return _file(Header("fusion", "1/1", 4, None, time.time()), body)


@pytest.mark.parametrize(
    ("declared", "why"),
    [
        (1 << 20, "array 'a0' inflates beyond its declared 1048576 bytes"),
        (2 << 30, f"bytes declared, more than the {MAX_INFLATED_BYTES} a state may have"),
    ],
    ids=["declares-1-MiB", "declares-2-GiB"],
)
def test_a_decompression_bomb_is_refused_within_its_declared_size(
    bomb: bytes, tmp_path: Path, caplog: pytest.LogCaptureFixture, declared: int, why: str
) -> None:
    (tmp_path / STATE).write_bytes(_bomb_file(bomb, declared))
    keeper_, engine = _restore(tmp_path)
    line = _line(caplog).getMessage()
    assert "refused (unreadable body (" in line and why in line, line
    # its header was read: its epoch still counts
    assert _clean(engine) and keeper_.epoch == 5


def test_an_array_header_that_declares_more_than_its_bytes_is_refused(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    (tmp_path / STATE).write_bytes(_lying_header_file())
    keeper_, engine = _restore(tmp_path)
    assert f"an array of shape ({1 << 28},) in 800 bytes" in _line(caplog).getMessage()
    assert _clean(engine) and keeper_.epoch == 5


# -- memory: at most twice what the file declares -----------------------------------------------

_MEASURE = """
import json, sys
from pathlib import Path
from service.state.fileformat import RefusedError, decode, read_file

def status(field):  # this process's memory (/proc: its own address space's, not inherited)
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) * 1024 for line in f if line.startswith(field + ":"))

before = status("VmRSS")
try:
    decode(read_file(Path(sys.argv[1])), "fusion", "1/1")
    why = None
except RefusedError as exc:
    why = str(exc)
print(json.dumps({"why": why, "growth": status("VmHWM") - before}))
"""
#: Peak memory a load may take beyond twice the declared size: the interpreter's own (the
#: JSON tree, the archive's bookkeeping, allocator slack).
ALLOWANCE = 32 << 20


def _big_state() -> bytes:
    """A whole file of 64 MB of arrays (a large network's registration memories)."""
    tree = {
        "p": np.arange(3_000_000, dtype=float).reshape(-1, 3),
        "s": np.arange(4_500_000, dtype=float).reshape(-1, 9),
        "pair": np.array([f"A-{i}\x1fB-{i}" for i in range(50_000)]),
    }
    return encode(Header("fusion", "1/1", 0, 1.0, time.time()), tree)


@pytest.mark.parametrize(
    "case", ["valid-64-MB", "bomb-declares-1-MiB", "bomb-declares-2-GiB", "oversized", "dev-zero", "fifo"]
)
def test_loading_any_file_takes_at_most_twice_its_declared_size(
    bomb: bytes, tmp_path: Path, case: str
) -> None:
    """Peak resident memory of reading and decoding one file, in a process of its own; the
    declared size is what the file's size (or, for a bomb, its archive) says it holds.  The
    peak is the address space's high-water mark (``VmHWM``): ``ru_maxrss`` starts from the
    forking parent's resident set, here the test process's."""
    path = tmp_path / STATE
    if case == "valid-64-MB":
        path.write_bytes(_big_state())
        declared = path.stat().st_size
    elif case.startswith("bomb"):
        size = 1 << 20 if case.endswith("1-MiB") else 2 << 30
        path.write_bytes(_bomb_file(bomb, size))
        declared = min(size, path.stat().st_size)  # the 2 GiB are refused before inflating
    elif case == "oversized":
        with open(path, "wb") as f:
            f.truncate(MAX_FILE_BYTES + 1)
        declared = 0  # refused on its size, before a byte is read
    elif case == "dev-zero":
        path.symlink_to("/dev/zero")
        declared = 0
    else:
        os.mkfifo(path)
        declared = 0
    res = subprocess.run(
        [sys.executable, "-c", _MEASURE, str(path)], cwd=REPO, capture_output=True, text=True, timeout=60
    )
    assert res.returncode == 0, res.stderr
    got = json.loads(res.stdout)
    assert (got["why"] is None) == (case == "valid-64-MB"), got
    assert got["growth"] <= 2 * declared + ALLOWANCE, (got, declared)


# -- whole files whose values cannot be believed ------------------------------------------------


def _source(tree: dict[str, Any], rid: str) -> dict[str, Any]:
    return next(s for s in tree["sources"] if s["source_id"] == rid)


def _clock_and_seq(header: Header, tree: dict[str, Any]) -> None:
    _source(tree, "A").update(time_s=9.9e9, seq=10**15)


def _clock(header: Header, tree: dict[str, Any]) -> None:
    _source(tree, "A")["time_s"] = 9.9e9


def _clock_everywhere(header: Header, tree: dict[str, Any]) -> Header:
    """Clock, the tree's data time and the header's data time all moved: consistent, and a
    century ahead of the wall clock the header says the file was written at."""
    _source(tree, "A")["time_s"] = tree["data_clock_s"] = 9.9e9
    return replace(header, data_clock_s=9.9e9)


def _written_in_the_future(header: Header, tree: dict[str, Any]) -> Header:
    _clock_everywhere(header, tree)
    return replace(header, data_clock_s=9.9e9, written_unix_s=9.9e9)


def _seq(header: Header, tree: dict[str, Any]) -> None:
    _source(tree, "B")["seq"] = MAX_KEPT_SEQ + 1


def _nan_bias(header: Header, tree: dict[str, Any]) -> None:
    tree["correlation"]["joint"]["bias"][0, 0] = np.nan


def _inf_covariance(header: Header, tree: dict[str, Any]) -> None:
    tree["correlation"]["joint"]["covariance"][1, 1] = np.inf


def _nan_row(header: Header, tree: dict[str, Any]) -> None:
    tree["correlation"]["memories"][0]["rows"]["s"][3, 0, 0] = np.nan


def _nan_site(header: Header, tree: dict[str, Any]) -> None:
    tree["sites"][1]["latitude_deg"] = math.nan


def _nan_joint_time(header: Header, tree: dict[str, Any]) -> None:
    tree["correlation"]["joint_time_s"] = math.nan


CRAFTED = [
    (_clock_and_seq, f"sources[0].seq 1000000000000000 (at most {MAX_KEPT_SEQ})"),
    (_clock, "sources[0].time_s 9900000000.0 is ahead of the file's data time (1763769690.0)"),
    (_clock_everywhere, "header data_clock_s 9900000000.0 is ahead of the wall clock of the write"),
    (_written_in_the_future, "header written_unix_s 9900000000 is ahead of the wall clock now"),
    (_seq, f"sources[1].seq {MAX_KEPT_SEQ + 1} (at most {MAX_KEPT_SEQ})"),
    (_nan_bias, "correlation.joint.bias is not finite (nan)"),
    (_inf_covariance, "correlation.joint.covariance is not finite (inf)"),
    (_nan_row, "correlation.memories[0].rows.s is not finite (nan)"),
    (_nan_site, "sites[1].latitude_deg is not finite (nan)"),
    (_nan_joint_time, "correlation.joint_time_s is not finite (nan)"),
]


@pytest.mark.parametrize(("edit", "why"), CRAFTED, ids=[e.__name__.strip("_") for e, _ in CRAFTED])
def test_a_whole_file_with_a_value_that_cannot_be_believed_is_refused_and_not_written_back(
    written: Path,
    tmp_path: Path,
    caplog: pytest.LogCaptureFixture,
    edit: Callable[[Header, dict[str, Any]], Header | None],
    why: str,
) -> None:
    crafted = _crafted(written, edit)
    (tmp_path / STATE).write_bytes(crafted)
    keeper_, engine = _restore(tmp_path)
    record = _line(caplog)
    assert record.levelno == logging.WARNING
    assert record.getMessage().startswith(f"state {tmp_path / STATE} refused (implausible content: {why}"), (
        record.getMessage()
    )
    assert "renamed to state.bin.refused, starting clean; track-id epoch 1" in record.getMessage()
    # nothing of it was taken, and nothing of it is in the file written at once
    assert _clean(engine) and keeper_.epoch == 1
    assert (tmp_path / "state.bin.refused").read_bytes() == crafted
    header, tree = decode(read_file(tmp_path / STATE), "fusion", "1/1")
    check(header, tree, time.time())
    assert header.epoch == 1 and tree["sources"] == [] and tree["sites"] == []
    assert tree["correlation"]["joint"] is None and header.data_clock_s is None


def test_after_a_crafted_clock_the_radar_is_taken_as_after_a_fresh_start(
    written: Path, stream: list[tuple[str, bytes]], tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """The case found: radar A's clock at 9.9e9 s and its ``seq`` at 10^15 (the checksum made
    right).  Taken, every one of A's batches after the restart was refused and the clock was
    written back; refused, the stream (its sites again, then the batches) is taken exactly as
    by a service started afresh."""
    (tmp_path / STATE).write_bytes(_crafted(written, _clock_and_seq))
    _, engine = _restore(tmp_path)
    assert "implausible content: sources[0].seq" in _line(caplog).getMessage()
    fresh = Engine(EngineConfig())
    fresh.restore_state(None, 1)  # a fresh start with the same epoch
    out, want = _feed(engine, stream), _feed(fresh, stream)
    assert _errors(out) == _errors(want) == []
    for rid in ("A", "B"):
        assert _radar(engine, rid) == _radar(fresh, rid)
    assert _radar(engine, "A")["batches"] == sum(k == "fusion/radar/A/plots" for k, _ in stream)
    assert _track_ids(out, "A") == _track_ids(want, "A")


def test_a_state_written_before_any_data_is_restored(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """The one value not finite that a whole state holds: the joint solve's time before any
    solve (-inf, unused)."""
    StateKeeper(tmp_path, "fusion", "1/1").restore(Engine(EngineConfig()))
    assert math.isinf(decode(read_file(tmp_path / STATE), "fusion", "1/1")[1]["correlation"]["joint_time_s"])
    caplog.clear()
    keeper_, _ = _restore(tmp_path)
    assert "restored 0 radar sites" in _line(caplog).getMessage() and keeper_.epoch == 1


# -- a directory that cannot be written --------------------------------------------------------


def test_a_start_that_cannot_write_its_state_keeps_its_epoch_in_the_old_file(
    written: Path, stream: list[tuple[str, bytes]], tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """The start's write fails (here the state would be beyond the size a start reads; a full
    disk fails the same way): the restored state serves, and the start's epoch goes into the
    old file's header in place, which stays whole, so the next start takes the one after."""
    shutil.copy(written, tmp_path / STATE)
    before = decode(written.read_bytes(), "fusion", "1/1")
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(keeper, "MAX_FILE_BYTES", 1000)
        keeper_, engine = _restore(tmp_path)
    record = _line(caplog)
    assert record.levelno == logging.WARNING
    assert "restored 2 radar sites" in record.getMessage()
    assert (
        "track-id epoch 1; the directory cannot be written (OSError: [Errno 27] a state of "
        in record.getMessage()
    )
    assert "going on read-only with the restored state" in record.getMessage()
    assert "epoch 1 written into the old file in place, so no track id repeats" in record.getMessage()
    assert keeper_.status()["failures"] == 1 and keeper_.status()["writes"] == 0
    assert len(engine.snapshot().biases()) == 2 and set(engine.snapshot().sites) == {"A", "B"}
    # the old file: whole, the new epoch, the old state
    header, tree = decode(read_file(tmp_path / STATE), "fusion", "1/1")
    assert header == replace(before[0], epoch=1)
    assert tree["sources"] == before[1]["sources"]
    # the service goes on; ids are of epoch 1, and the next start takes epoch 2
    out = _feed(engine, _split(stream)[1])
    assert _errors(out) == [] and all(int(t.rsplit("-", 1)[1]) > 10**9 for t in _track_ids(out, "A"))
    caplog.clear()
    keeper_, engine = _restore(tmp_path)
    assert keeper_.epoch == 2 and "restored 2 radar sites" in _line(caplog).getMessage()


def test_a_start_with_no_file_that_cannot_write_says_its_ids_may_come_again(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(keeper, "MAX_FILE_BYTES", 100)
        keeper_, engine = _restore(tmp_path)
    record = _line(caplog)
    assert record.levelno == logging.ERROR
    assert record.getMessage().startswith(
        f"state {tmp_path / STATE}: none yet, starting clean; track-id epoch 0;"
    )
    assert (
        "until a write succeeds, a later start may give this start's track ids again" in record.getMessage()
    )
    assert not (tmp_path / STATE).exists() and not list(tmp_path.iterdir())
    assert keeper_.epoch == 0 and keeper_.status()["failures"] == 1 and _clean(engine)


# -- the epoch's bound ---------------------------------------------------------------------------


def test_the_last_epoch_is_taken_then_a_start_is_refused_rather_than_repeat_ids(
    written: Path, stream: list[tuple[str, bytes]], tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    (tmp_path / STATE).write_bytes(_crafted(written, lambda h, t: replace(h, epoch=MAX_EPOCH - 2)))
    keeper_, engine = _restore(tmp_path)
    assert keeper_.epoch == MAX_EPOCH - 1
    record = _line(caplog)
    assert record.levelno == logging.WARNING
    assert f"track-id epoch {MAX_EPOCH - 1} (0 more starts before the epochs run out" in record.getMessage()
    # the last epoch's ids: still exact as a float64
    out = _feed(engine, _split(stream)[1])
    ids = _track_ids(out, "A")
    assert ids and all((MAX_EPOCH - 1) * 10**9 < int(t.rsplit("-", 1)[1]) < 2**53 for t in ids)
    keeper_.save(engine)
    on_disk = (tmp_path / STATE).read_bytes()
    caplog.clear()
    with pytest.raises(EpochsExhaustedError) as refused:
        _restore(tmp_path)
    why = (
        f"track-id epochs exhausted (the file's epoch is {MAX_EPOCH - 1}, the last there is "
        f"{MAX_EPOCH - 1}: a new epoch could give ids an earlier start gave): delete "
        f"{tmp_path / STATE} to start afresh"
    )
    assert refused.value.strerror.startswith(why)
    assert _line(caplog).levelno == logging.ERROR and why in _line(caplog).getMessage()
    assert (tmp_path / STATE).read_bytes() == on_disk  # untouched: the operator decides


@pytest.mark.parametrize("whole", [True, False], ids=["whole", "corrupt"])
def test_an_epoch_beyond_the_bound_is_not_taken_for_zero(written: Path, tmp_path: Path, whole: bool) -> None:
    """A file an older service wrote at epoch 10^6 (it went one past): refused as the last
    epoch is, not read as no epoch (which started again from 0)."""
    data = bytearray(_crafted(written, lambda h, t: replace(h, epoch=MAX_EPOCH)))
    if not whole:
        data[len(data) // 2] ^= 0x01
    (tmp_path / STATE).write_bytes(bytes(data))
    with pytest.raises(EpochsExhaustedError, match=f"the file's epoch is {MAX_EPOCH}, the last there is"):
        _restore(tmp_path)


# -- the service as an operator runs it ------------------------------------------------------


@contextmanager
def _service(command: list[str], timeout: float = 60.0) -> Iterator[subprocess.Popen[str]]:
    """``command`` (the service, perhaps under a wrapper that ``exec``s it: one pid) with no
    TOPOFUSION_* setting; killed by its pid if a test failed before stopping it."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("TOPOFUSION_")}
    env["PYTHONUNBUFFERED"] = "1"
    proc = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
    try:
        yield proc
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=10)
        if proc.stdout is not None:
            proc.stdout.close()


def _ready(proc: subprocess.Popen[str], url: str) -> None:
    wait_for(lambda: _http_ready(url) or proc.poll() is not None, timeout=60)
    assert proc.poll() is None, proc.stdout.read() if proc.stdout else ""


def _stop(proc: subprocess.Popen[str]) -> str:
    proc.send_signal(signal.SIGTERM)
    out, _ = proc.communicate(timeout=30)
    assert proc.returncode == 0, out
    return out


def _run_args(router: str, port: int, directory: Path) -> list[str]:
    args = ["run", "--mode", "client", "--connect", router, "--http-port", str(port)]
    return [*args, "--prefix", "fusion", "--state-dir", str(directory)]


def test_a_fifo_for_a_state_file_does_not_hang_the_service(router: str, tmp_path: Path) -> None:
    directory = tmp_path / "state"
    directory.mkdir()
    os.mkfifo(directory / STATE)
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    with _service([TOPOFUSION, *_run_args(router, port, directory)]) as proc:
        _ready(proc, url)
        state = httpx.get(url + "/status", timeout=5).json()["state"]
        assert state["epoch"] == 0 and state["writes"] == 1 and state["failures"] == 0
        assert httpx.get(url + "/radars", timeout=5).json() == []
        out = _stop(proc)
    assert (
        f"state {directory / STATE} refused (not a regular file but a FIFO): renamed to "
        "state.bin.refused, starting clean; track-id epoch 0"
    ) in out, out
    assert stat.S_ISFIFO(os.lstat(directory / "state.bin.refused").st_mode)
    assert decode(read_file(directory / STATE), "fusion", "1/1")[0].epoch == 0


@pytest.mark.slow
def test_a_second_process_on_one_state_directory_is_refused(router: str, tmp_path: Path) -> None:
    """Two processes on one directory (shared by mistake, or an old one still running beside
    its replacement) would take the same track-id epoch and give the same ids: the second is
    refused at start, naming the first; once the first has stopped, a start takes it."""
    directory = tmp_path / "state"
    first_port, second_port = free_port(), free_port()
    with _service([TOPOFUSION, *_run_args(router, first_port, directory)]) as first:
        _ready(first, f"http://127.0.0.1:{first_port}")
        with _service([TOPOFUSION, *_run_args(router, second_port, directory)]) as second:
            out, _ = second.communicate(timeout=60)
        assert second.returncode == 2, out
        said = f"state directory {directory} cannot be used: in use by another process (pid {first.pid})"
        assert said in out, out
        _stop(first)
    with _service([TOPOFUSION, *_run_args(router, second_port, directory)]) as again:
        _ready(again, f"http://127.0.0.1:{second_port}")
        assert httpx.get(f"http://127.0.0.1:{second_port}/status", timeout=5).json()["state"]["epoch"] == 1
        _stop(again)


def test_the_lock_never_writes_through_a_link(tmp_path: Path) -> None:
    """A ``state.lock`` that is a link (a hostile or botched directory): the lock is the
    directory's own, and the pid is never written through the link (its target was truncated
    and overwritten, a dangling one created outside the directory)."""
    from service.state.lock import LOCK_FILE, lock_directory, release_directory

    victim, elsewhere = tmp_path / "victim.txt", tmp_path / "created-elsewhere"
    victim.write_text("precious data")
    for name, target in (("one", victim), ("two", elsewhere)):
        directory = tmp_path / name
        directory.mkdir()
        (directory / LOCK_FILE).symlink_to(target)
        lock_directory(directory)
        release_directory(directory)
    assert victim.read_text() == "precious data" and not elsewhere.exists()


def test_config_refuses_a_state_directory_run_would_refuse(written: Path, tmp_path: Path) -> None:
    """``topofusion config`` says what a start would: a path through a file, a file at the
    last epoch, a link to nothing (it said "configuration is valid" to all)."""
    a_file = tmp_path / "a-file"
    a_file.write_text("")
    last = tmp_path / "last"
    last.mkdir()
    (last / STATE).write_bytes(_crafted(written, lambda h, t: replace(h, epoch=MAX_EPOCH - 1)))
    env = {k: v for k, v in os.environ.items() if not k.startswith("TOPOFUSION_")}
    dangling, loop = tmp_path / "dangling", tmp_path / "loop"
    dangling.symlink_to(tmp_path / "nowhere")
    loop.symlink_to(loop)
    for directory, said in (
        (a_file / "sub", f"{a_file} is not a directory"),
        (last, "track-id epochs exhausted"),
        (dangling, f"{dangling} is a link to nothing"),
        (loop / "sub", f"{loop} is a link to nothing"),
    ):
        res = subprocess.run(
            [TOPOFUSION, "config"],
            capture_output=True,
            text=True,
            env={**env, "TOPOFUSION_STATE_DIR": str(directory)},
            timeout=60,
        )
        assert res.returncode == 2, res.stderr
        assert f"TOPOFUSION_STATE_DIR {directory} cannot be used: " in res.stderr and said in res.stderr


#: Inside a mount namespace of its own (``unshare``): a 128 kB tmpfs over the state directory,
#: the state file copied in and the rest filled, then the service (``exec``: the same pid).
FULL_DISK = (
    'mount -t tmpfs -o size=128k tmpfs "$1" && cp "$2" "$1/state.bin" && '
    '{ cat /dev/zero > "$1/filler" 2>/dev/null || true; } && shift 2 && exec "$@"'
)
#: Inside a mount namespace of its own: the state file copied in, then the state directory
#: bound over itself read-only, then the service (``exec``: the same pid).
READ_ONLY = (
    'cp "$2" "$1/state.bin" && mount --bind "$1" "$1" && mount -o remount,bind,ro "$1" && '
    'shift 2 && exec "$@"'
)
#: The service under a file-size limit (``RLIMIT_FSIZE``) below the state file's size: every
#: write of it fails (``EFBIG``; Python ignores the signal that comes with it).
FILE_SIZE_LIMIT = (
    "import os, resource, sys; n = int(sys.argv[1]); "
    "resource.setrlimit(resource.RLIMIT_FSIZE, (n, n)); os.execv(sys.argv[2], sys.argv[2:])"
)


def _namespaces() -> bool:
    """Whether this machine lets a process mount a tmpfs in namespaces of its own."""
    if shutil.which("unshare") is None:
        return False
    probe = "mount -t tmpfs tmpfs /mnt 2>/dev/null || mount -t tmpfs tmpfs /tmp"
    res = subprocess.run(
        ["unshare", "--user", "--map-root-user", "--mount", "sh", "-c", probe],
        capture_output=True,
        timeout=10,
    )
    return res.returncode == 0


@pytest.mark.parametrize("how", ["disk-full", "read-only-mount", "file-size-limit"])
def test_a_restart_that_cannot_write_goes_on_read_only(
    router: str, written: Path, tmp_path: Path, how: str
) -> None:
    """The state directory cannot take the start's write: the service restores the file,
    answers with what it restored, says so, and stops normally (its writes failing)."""
    directory = tmp_path / "state"
    directory.mkdir()
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    service = [TOPOFUSION, *_run_args(router, port, directory)]
    if how in ("disk-full", "read-only-mount"):
        if not _namespaces():
            pytest.skip("no user and mount namespaces here: the file-size limit case stands in")
        script = FULL_DISK if how == "disk-full" else READ_ONLY
        command = ["unshare", "--user", "--map-root-user", "--mount", "sh", "-c", script, "sh"]
        command += [str(directory), str(written), *service]
        error = (
            "OSError: [Errno 28] No space left on device"
            if how == "disk-full"
            else "OSError: [Errno 30] Read-only file system"  # (the lock is taken all the same)
        )
    else:
        shutil.copy(written, directory / STATE)
        limit = 16 << 10
        assert written.stat().st_size > limit
        command = [sys.executable, "-c", FILE_SIZE_LIMIT, str(limit), *service]
        error = "OSError: [Errno 27] File too large"
    with _service(command) as proc:
        _ready(proc, url)
        # what was restored serves at once: both radars' sites and biases
        assert sorted(b["radar_id"] for b in httpx.get(url + "/biases", timeout=5).json()) == ["A", "B"]
        assert [r["radar_id"] for r in httpx.get(url + "/radars", timeout=5).json()] == ["A", "B"]
        state = httpx.get(url + "/status", timeout=5).json()["state"]
        assert state["epoch"] == 1 and state["writes"] == 0 and state["failures"] == 1
        out = _stop(proc)
    assert "restored 2 radar sites" in out, out
    assert f"track-id epoch 1; the directory cannot be written ({error}" in out, out
    assert "going on read-only with the restored state" in out, out
    assert f"state {directory / STATE} not written: OSError" in out  # the final write, at the stop
    if how == "disk-full":
        assert "epoch 1 written into the old file in place, so no track id repeats" in out, out
    else:
        # the file's end is beyond the limit too (or the mount read-only): not even the epoch,
        # and the file is as it was
        assert f"epoch 1 could not be kept ({error}" in out and "until a write succeeds" in out, out
        assert (directory / STATE).read_bytes() == written.read_bytes()


def test_a_start_past_the_last_epoch_is_refused_with_a_clear_line(written: Path, tmp_path: Path) -> None:
    directory = tmp_path / "state"
    directory.mkdir()
    data = _crafted(written, lambda h, t: replace(h, epoch=MAX_EPOCH - 1))
    (directory / STATE).write_bytes(data)
    env = {k: v for k, v in os.environ.items() if not k.startswith("TOPOFUSION_")}
    res = subprocess.run(
        [TOPOFUSION, "run", "--state-dir", str(directory), "--http-port", "0", "--mode", "client"],
        capture_output=True,
        text=True,
        timeout=60,
        env=env,
    )
    assert res.returncode == 2, res.stderr
    assert (
        f"topofusion: state directory {directory} cannot be used: track-id epochs exhausted (the "
        f"file's epoch is {MAX_EPOCH - 1}, the last there is {MAX_EPOCH - 1}"
    ) in res.stderr, res.stderr
    assert f"delete {directory / STATE} to start afresh, track ids then count from 1 again" in res.stderr
    assert (directory / STATE).read_bytes() == data
