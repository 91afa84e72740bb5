"""When a replay into a live service is done (service/recording/completion.py)."""

from __future__ import annotations

import json
from typing import Any

from service.recording.completion import RecordingEnd, merged_status, wait_complete
from service.recording.reader import RecordedMessage


def _message(key: str, kind: str, time_s: float, seq: int = 0) -> RecordedMessage:
    body = json.dumps({"time_s": time_s, "seq": seq}).encode()
    return RecordedMessage(key, kind, body, 0, 0, 0)  # type: ignore[arg-type]


def test_with_a_prefix_only_the_batches_the_service_takes_count() -> None:
    """A replay's end follows the service's sequencer: a batch an hour ahead of the others'
    clock, one beyond the contract's time range, a repeated seq, plots of a radar whose site
    was not sent: none moves the end; the repeated seq is counted as the recording's own."""
    end = RecordingEnd(prefix="f")
    for r in "AB":
        end.add(RecordedMessage(f"f/radar/{r}/site", "site", b"{}", 0, 0, 0))
    t0 = 1.7e9
    for seq, t in enumerate((0.0, 4.0, 8.0), start=1):
        for r in "AB":
            end.add(_message(f"f/radar/{r}/plots", "plots", t0 + t, seq))
        if seq == 2:
            end.add(_message("f/radar/A/plots", "plots", t0 + 3_600.0, 9))  # an hour ahead
            end.add(_message("f/radar/A/plots", "plots", 1e11, 10))  # beyond the time range
            end.add(_message("f/radar/B/plots", "plots", t0 + 4.0, 2))  # sent twice
            end.add(_message("f/radar/C/plots", "plots", t0 + 900.0, 1))  # no site
    assert end.target_s() == t0 + 8.0
    assert end.duplicates == 1


def test_the_end_is_the_lowest_last_time_of_the_sources_still_reporting() -> None:
    end = RecordingEnd()
    assert end.target_s() is None
    for key, t in [("f/radar/A/plots", 100.0), ("f/radar/B/plots", 104.0), ("f/radar/A/plots", 108.0)]:
        end.add(_message(key, "plots", t))
    end.add(_message("f/ais/x/reports", "ais", 107.0))
    end.add(_message("f/radar/C/plots", "plots", 50.0))  # fell silent long before: holds nothing back
    end.add(_message("f/radar/A/site", "site", 999.0))  # a site moves no clock
    end.add(RecordedMessage("f/radar/B/plots", "plots", b"not json", 0, 0, 0))
    assert end.target_s() == 104.0


def test_waits_until_complete_and_nothing_pending() -> None:
    answers: list[dict[str, Any] | None] = [
        None,
        {"outputs_time_s": 90.0, "correlation": {"pending": 3}},
        {"outputs_time_s": 104.0, "correlation": {"pending": 2}},
        {"outputs_time_s": 104.5, "correlation": {"pending": 0}},
    ]
    now = [0.0]
    said: list[str] = []

    def sleep(s: float) -> None:
        now[0] += s

    done, seen, answered = wait_complete(
        lambda: answers.pop(0), 104.0, 60.0, said.append, clock=lambda: now[0], sleep=sleep
    )
    assert (done, seen, answered) == (True, 104.5, True)


def test_gives_up_after_the_timeout_and_when_nobody_answers() -> None:
    now = [0.0]

    def sleep(s: float) -> None:
        now[0] += s

    behind = {"outputs_time_s": 10.0, "correlation": {"pending": 0}}
    done, seen, answered = wait_complete(lambda: behind, 50.0, 3.0, lambda _: None, lambda: now[0], sleep)
    assert (done, seen, answered) == (False, 10.0, True) and now[0] >= 3.0
    now[0] = 0.0
    done, seen, answered = wait_complete(lambda: None, 50.0, 60.0, lambda _: None, lambda: now[0], sleep)
    assert (done, seen, answered) == (False, None, False) and now[0] < 10.0


def test_partitioned_workers_are_complete_through_the_lowest_of_their_times() -> None:
    """Each worker answers ``{prefix}/status``: the outputs are complete once every one is."""
    one = {"outputs_time_s": 120.0, "correlation": {"pending": 0}}
    two = {"outputs_time_s": 104.0, "correlation": {"pending": 2}}
    assert merged_status([one, two]) == {"outputs_time_s": 104.0, "correlation": {"pending": 2}}
    starting = {"outputs_time_s": None, "correlation": {"pending": 0}}
    assert merged_status([one, starting])["outputs_time_s"] is None
