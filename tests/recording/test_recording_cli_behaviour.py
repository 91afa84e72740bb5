"""The tools as a newcomer meets them: started before the router, replaying twice."""

from __future__ import annotations

import argparse
import threading
from pathlib import Path

import pytest
from recording_helpers import PREFIX, foreign_mcap, plots, site, wait_for, wait_subscribed

from service.recording import add_record_arguments, add_replay_arguments, record_main, replay_main
from service.transport.session import ZenohOptions, open_session
from tests.support import free_port, running_service


def _parser(add: object) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser()
    add(p)  # type: ignore[operator]
    return p


def _wait_listening(options: ZenohOptions) -> None:
    """Until the service (started) subscribes to radar A's plots: a replay sent before it
    would be lost on nobody."""
    probe = open_session(options)
    try:
        wait_subscribed(probe, f"{PREFIX}/radar/A/plots")
    finally:
        probe.close()


def test_recorder_started_before_its_router_waits_for_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    options = ZenohOptions(mode="client", connect=(endpoint,))
    out = tmp_path / "late.mcap"
    args = _parser(add_record_arguments).parse_args(["--out", str(out), "--duration", "30"])
    stop = threading.Event()
    result: dict[str, int] = {}
    thread = threading.Thread(target=lambda: result.setdefault("rc", record_main(args, options, stop)))
    thread.start()
    try:
        wait_for(lambda: "waiting for the Zenoh router" in capsys.readouterr().err, timeout=10)
        router = open_session(ZenohOptions(mode="router", listen=(endpoint,)))
        try:
            pub = open_session(options)
            try:
                wait_subscribed(pub, f"{PREFIX}/radar/A/plots", timeout=20)
                # the file's header comes first: stop only once the message is written after it
                wait_for(lambda: out.exists() and out.stat().st_size > 0, timeout=10)
                header = out.stat().st_size
                pub.put(f"{PREFIX}/radar/A/plots", plots("A", 1, 1e9))
                wait_for(lambda: out.stat().st_size > header, timeout=10)
            finally:
                pub.close()
            stop.set()
            thread.join(timeout=20)
        finally:
            router.close()
    finally:
        stop.set()
        thread.join(timeout=20)
    assert result["rc"] == 0


def test_a_second_replay_into_the_same_service_says_it_was_rejected(
    tmp_path: Path, router: str, capsys: pytest.CaptureFixture[str]
) -> None:
    recording = tmp_path / "run.mcap"
    msgs = [(f"{PREFIX}/radar/A/site", site("A"), 1)]
    msgs += [(f"{PREFIX}/radar/A/plots", plots("A", i, 1e9 + i), 10 + i) for i in range(1, 6)]
    foreign_mcap(recording, msgs)
    options = ZenohOptions(mode="client", connect=(router,))
    args = _parser(add_replay_arguments).parse_args([str(recording), "--speed", "0"])
    with running_service(router) as svc:
        _wait_listening(options)
        assert replay_main(args, options) == 0
        wait_for(lambda: svc.http.get("/status").json()["radars"][0]["batches"] == 5)
        capsys.readouterr()
        assert replay_main(args, options) == 1
        err = capsys.readouterr().err
        assert "5 duplicate_seq" in err and "already took this recording" in err


def test_a_recording_s_own_duplicates_are_not_blamed_on_the_service(
    tmp_path: Path, router: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """A source that sent a batch twice is recorded twice, and a fresh service rejects the
    second copy as the live one did: the replay says so, succeeds, and does not tell the user
    the service already took the recording.  At --speed 0 the summary comes after the wait,
    once the service has worked through its queue, so it counts every rejection."""
    recording = tmp_path / "twice.mcap"
    msgs = [(f"{PREFIX}/radar/A/site", site("A"), 1)]
    msgs += [(f"{PREFIX}/radar/A/plots", plots("A", i, 1e9 + i), 10 + i) for i in range(1, 6)]
    msgs += [(f"{PREFIX}/radar/A/plots", plots("A", 3, 1e9 + 3), 20)]  # the third again
    msgs += [(f"{PREFIX}/radar/A/plots", plots("A", i, 1e9 + i), 20 + i) for i in range(6, 9)]
    foreign_mcap(recording, msgs)
    options = ZenohOptions(mode="client", connect=(router,))
    args = _parser(add_replay_arguments).parse_args([str(recording), "--speed", "0", "--wait", "30"])
    with running_service(router):
        _wait_listening(options)
        assert replay_main(args, options) == 0
        err = capsys.readouterr().err
        assert "the service rejected messages of this replay: 1 duplicate_seq" in err, err
        assert "1 of the messages repeat an earlier seq of their key" in err
        assert "already took this recording" not in err
        capsys.readouterr()
        assert replay_main(args, options) == 1  # a second replay: every batch taken before
        assert "already took this recording" in capsys.readouterr().err


def test_a_batch_the_service_refuses_moves_no_end_of_the_replay(
    tmp_path: Path, router: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """One batch stamped far in the future (a radar's clock fault, refused out_of_range by the
    service) must not become the end the replay waits for: the replay ends when the service is
    complete through the honest batches, with exit 0, instead of waiting out --wait."""
    recording = tmp_path / "future.mcap"
    t0 = 1e9
    msgs = [(f"{PREFIX}/radar/A/site", site("A"), 1), (f"{PREFIX}/radar/B/site", site("B", lon=121.5), 2)]
    for i in range(1, 9):
        msgs += [
            (f"{PREFIX}/radar/{r}/plots", plots(r, i, t0 + 2.0 * i), 10 + 2 * i + k)
            for k, r in enumerate("AB")
        ]
        if i == 4:
            msgs += [(f"{PREFIX}/radar/A/plots", plots("A", 100, 1e11), 19)]  # the fault
    foreign_mcap(recording, msgs)
    options = ZenohOptions(mode="client", connect=(router,))
    args = _parser(add_replay_arguments).parse_args([str(recording), "--speed", "0", "--wait", "20"])
    with running_service(router):
        _wait_listening(options)
        assert replay_main(args, options) == 0
    err = capsys.readouterr().err
    assert "1 out_of_range" in err, err
    assert "the service's outputs are complete through data time" in err
