"""``topofusion record`` and ``topofusion replay``: argument parsing edges and entry points.

The command line (``service/cli/tools.py``) adds the common Zenoh flags (``--mode`` defaulting to
client, ``--listen``, ``--connect``, ``--zenoh-config``, ``--prefix``) and calls these functions.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import json
import signal
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import zenoh

from service.output_files import check_writable
from service.recording.completion import RecordingEnd, service_statuses, wait_for_outputs
from service.recording.keys import KeyFilter
from service.recording.reader import RecordedMessage, RecordingError
from service.recording.recorder import DEFAULT_QUEUE_BYTES, DEFAULT_QUEUE_SAMPLES, record
from service.recording.replay import ReplayOptions, preflight, replay
from service.transport.session import OpenCancelledError, ZenohOptions, open_tool_session
from service.wire.vocabulary import METHODS


def _non_negative(text: str) -> float:
    value = float(text)
    if not value >= 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {text}")
    return value


def _positive(text: str) -> float:
    value = float(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {text}")
    return value


def add_record_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", required=True, metavar="FILE.mcap", help="MCAP file to write")
    parser.add_argument("--key", metavar="EXPR", help="key expression to record (default {prefix}/**)")
    parser.add_argument(
        "--duration", type=_positive, metavar="S", help="stop after S seconds (default: at SIGINT/SIGTERM)"
    )
    parser.add_argument(
        "--queue-samples", type=int, default=DEFAULT_QUEUE_SAMPLES, help="writer queue bound, samples"
    )
    parser.add_argument(
        "--queue-bytes", type=int, default=DEFAULT_QUEUE_BYTES, help="writer queue bound, bytes"
    )


def add_replay_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "file", metavar="FILE.mcap", help="recording to replay (any MCAP file of the contract's shape)"
    )
    parser.add_argument(
        "--speed",
        type=_non_negative,
        default=1.0,
        metavar="X",
        help="x the recorded timing; 0 = as fast as the receiver takes it (default 1)",
    )
    parser.add_argument("--key", metavar="EXPR", help="replay only keys intersecting EXPR")
    parser.add_argument(
        "--start", type=_non_negative, metavar="S", help="skip the first S seconds of the recording"
    )
    parser.add_argument(
        "--end", type=_non_negative, metavar="S", help="stop S seconds after the recording's start"
    )
    parser.add_argument("--loop", action="store_true", help="start over at the end until stopped")
    parser.add_argument(
        "--all-keys",
        action="store_true",
        help="also replay the service's own outputs (tracks, pairs, errors, status); default: inputs only",
    )
    parser.add_argument(
        "--progress",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="progress line on stderr (default: on long replays)",
    )
    parser.add_argument(
        "--wait-service",
        type=_non_negative,
        default=0.0,
        metavar="S",
        help="before the first message, wait up to S s for a service to answer {prefix}/status (default 0)",
    )
    parser.add_argument(
        "--wait",
        type=_non_negative,
        default=120.0,
        metavar="S",
        help="after the last message, wait up to S seconds until the service reports its outputs "
        "complete through the recording's end (Status.outputs_time_s); 0: do not wait (default 120)",
    )
    off = parser.add_argument_group("offline replay (no Zenoh)")
    off.add_argument("--offline", action="store_true", help="feed an in-process engine instead of publishing")
    off.add_argument("--out", metavar="RESULT.json", help="offline result file (default: stdout)")
    off.add_argument("--method", choices=METHODS, help="correlation method (default svd-topology)")
    off.add_argument("--window", type=_positive, metavar="S", help="sliding window, seconds of data time")
    off.add_argument("--sites", metavar="FILE", help="JSON file with a list of RadarSite")
    off.add_argument("--config", metavar="FILE", help="engine parameters, TOML/YAML/JSON (as for run)")
    off.add_argument(
        "--compare",
        action="store_true",
        help="compare the confirmed tracks and pairs with the service's last outputs in the recording "
        "(exit status 1 when they differ)",
    )


@contextlib.contextmanager
def _stop_on_signals(stop: threading.Event) -> Iterator[None]:
    """SIGINT/SIGTERM set ``stop`` (main thread only; elsewhere the caller stops us)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous: dict[signal.Signals, Any] = {}

    def handler(signum: int, _frame: object) -> None:
        stop.set()

    for sig in (signal.SIGINT, signal.SIGTERM):
        previous[sig] = signal.signal(sig, handler)
    try:
        yield
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)


def _session_or_stop(
    options: ZenohOptions, tool: str, stop: threading.Event, nothing: str
) -> zenoh.Session | None:
    """The tool's session, or None (said on stderr) when SIGINT/SIGTERM came while it waited
    for its router: the tool then ends with status 0, having done ``nothing``."""
    try:
        with _stop_on_signals(stop):
            return open_tool_session(options, tool, stop)
    except OpenCancelledError:
        print(f"{tool}: stopped while waiting for the Zenoh router; {nothing}", file=sys.stderr)
        return None


def _prefix(args: argparse.Namespace) -> str:
    return str(getattr(args, "prefix", None) or "fusion")


def record_main(
    args: argparse.Namespace, zenoh_options: ZenohOptions, stop: threading.Event | None = None
) -> int:
    """Record until SIGINT/SIGTERM (or ``stop``) or ``--duration``; prints the report.

    Exit status 0, or 1 when samples were dropped or the file could not be written.
    """
    prefix = _prefix(args)
    key_expr = args.key or f"{prefix}/**"
    stop = stop or threading.Event()
    _check_output(Path(args.out))  # before connecting: a typo in --out must not cost a run
    KeyFilter(key_expr)  # (a ValueError naming a --key Zenoh would refuse)
    session = _session_or_stop(zenoh_options, "record", stop, "nothing recorded")
    if session is None:
        return 0
    try:
        print(f"recording {key_expr} to {args.out} (Ctrl-C to stop)", file=sys.stderr, flush=True)
        with _stop_on_signals(stop):
            report = record(
                session,
                args.out,
                key_expr,
                prefix,
                duration_s=args.duration,
                stop=stop,
                max_queue_samples=getattr(args, "queue_samples", DEFAULT_QUEUE_SAMPLES),
                max_queue_bytes=getattr(args, "queue_bytes", DEFAULT_QUEUE_BYTES),
            )
    finally:
        session.close()
    for line in report.lines():
        print(line, file=sys.stderr if line.startswith(("WARNING", "ERROR")) else sys.stdout, flush=True)
    return 1 if report.dropped or report.error else 0


def _check_output(path: Path) -> None:
    """Raise ValueError (the command's exit status 2) unless ``path`` can be written."""
    check_writable(path, "record: --out")


def _replay_options(args: argparse.Namespace) -> ReplayOptions:
    return ReplayOptions(
        speed=args.speed,
        key_expr=args.key,
        start_s=args.start,
        end_s=args.end,
        include_outputs=args.all_keys,
        loop=args.loop,
    )


def _offline_engine(args: argparse.Namespace, prefix: str) -> Any:
    from service.engine import Engine
    from service.settings import Settings, engine_config

    overrides = {
        key: value
        for key, value in (
            ("method", args.method),
            ("window_s", args.window),
            ("sites", args.sites),
            ("config", args.config),
        )
        if value is not None
    }
    settings = Settings(**overrides)  # environment (TOPOFUSION_*) under the flags, like `run`
    return Engine(replace(engine_config(settings), prefix=prefix))


def replay_main(
    args: argparse.Namespace, zenoh_options: ZenohOptions, stop: threading.Event | None = None
) -> int:
    """Replay over Zenoh, or offline into an engine; 2 with a clear message on an unusable file."""
    prefix = _prefix(args)
    stop = stop or threading.Event()
    try:
        options = _replay_options(args)
        if args.wait_service < 0:
            raise ValueError("--wait-service must be >= 0")
        if args.offline:
            if args.loop or args.all_keys:
                raise ValueError("--offline feeds the inputs once: --loop and --all-keys do not apply")
            if args.out is not None:
                check_writable(Path(args.out), "--out")  # before the replay, not after it
            return _offline_main(args, prefix, options)
        if args.out is not None:
            raise ValueError("--out is for --offline (the result file); a Zenoh replay publishes instead")
        if args.compare:
            raise ValueError("--compare is for --offline (it compares an offline replay's result)")
        from service.recording.publisher import ZenohReplayPublisher

        preflight(args.file, prefix, options)  # a file that cannot be replayed is refused before connecting
        session = _session_or_stop(zenoh_options, "replay", stop, "nothing replayed")
        if session is None:
            return 0
        rejections = RejectionWatch(session, prefix)
        end = RecordingEnd(prefix=prefix)
        own = 0  # the recording's own repeated seq (--loop sends it again: its repeats are ours)
        try:
            if args.wait_service > 0:
                _wait_for_service(session, prefix, args.wait_service, stop)
            with _stop_on_signals(stop), ZenohReplayPublisher(session) as publish:

                def publish_and_note(message: RecordedMessage) -> None:
                    publish(message)
                    end.add(message)

                report = replay(
                    args.file, publish_and_note, prefix, options, stop=stop, progress=args.progress
                )
            for line in report.lines():
                print(line, file=sys.stderr, flush=True)
            complete = True
            if args.wait > 0 and not stop.is_set() and not options.loop:
                complete = wait_for_outputs(session, prefix, end, args.wait)
            # After the wait: a service still working through its queue (a replay at --speed 0)
            # rejects the last messages after the replay has sent them; done, it has said all.
            rejections.settle()
            own = 0 if options.loop else end.duplicates
            for line in rejections.lines(own):
                print(line, file=sys.stderr, flush=True)
        finally:
            rejections.close()
            session.close()
    except (RecordingError, FileNotFoundError, IsADirectoryError, PermissionError, ValueError) as exc:
        print(f"topofusion replay: {exc}", file=sys.stderr, flush=True)
        return 2
    return 1 if rejections.taken_before(own) or not complete else 0


def _wait_for_service(session: Any, prefix: str, wait_s: float, stop: threading.Event) -> None:
    """``--wait-service``: before the first message, until a service answers (saying so)."""
    say = functools.partial(print, file=sys.stderr, flush=True)
    say(f"replay: asking the service for {prefix}/status (up to {wait_s:g} s)")
    if service_statuses(session, prefix, wait_s, stop):
        say("replay: the service answers: replaying")
    else:
        say(f"replay: no service answered {prefix}/status within {wait_s:g} s: replaying anyway")


class RejectionWatch:
    """The service's rejections (``{prefix}/errors``) while a replay (or a simulation) sends.

    A service that already took a recording rejects every batch of a second replay as a
    duplicate ``seq``: the replay then says so and exits 1 rather than reporting success
    (``simulate`` likewise, when restarted behind the service's data clock).
    """

    #: After the last message, wait until no rejection came for this long (s), at most ``SETTLE_MAX_S``.
    SETTLE_QUIET_S, SETTLE_MAX_S = 0.5, 5.0

    #: What a replay's duplicates mean, and what to do about them.
    REPLAY_DUPLICATES = (
        "the service already took this recording; restart it (or replay into a fresh one) to process it again"
    )

    def __init__(
        self, session: Any, prefix: str, what: str = "this replay", duplicates: str = REPLAY_DUPLICATES
    ) -> None:
        self.what = what
        self.duplicates = duplicates
        self.by_reason: dict[str, int] = {}
        self._last = time.monotonic()
        self._lock = threading.Lock()
        self._sub = session.declare_subscriber(f"{prefix}/errors", self._on_sample)

    def _on_sample(self, sample: Any) -> None:
        try:
            reason = str(json.loads(sample.payload.to_bytes())["reason"])
        except (ValueError, KeyError, TypeError):
            return
        with self._lock:
            self.by_reason[reason] = self.by_reason.get(reason, 0) + 1
            self._last = time.monotonic()

    def settle(self) -> None:
        """Wait for the rejections still on their way (the replay's last messages were sent)."""
        end = time.monotonic() + self.SETTLE_MAX_S
        with self._lock:
            self._last = max(self._last, time.monotonic())
        while time.monotonic() < end and time.monotonic() - self._last < self.SETTLE_QUIET_S:
            time.sleep(0.05)

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self._sub.undeclare()

    def taken_before(self, own_duplicates: int = 0) -> bool:
        """Whether the service had taken these messages before: more ``duplicate_seq``
        rejections than the messages' own duplicates (``own_duplicates``: a recording of a
        source that sent a batch twice holds it twice, and a fresh service rejects it too)."""
        return self.by_reason.get("duplicate_seq", 0) > own_duplicates

    def lines(self, own_duplicates: int = 0) -> list[str]:
        if not self.by_reason:
            return []
        counts = ", ".join(f"{n} {r}" for r, n in sorted(self.by_reason.items()))
        out = [f"the service rejected messages of {self.what}: {counts}"]
        if own_duplicates and self.by_reason.get("duplicate_seq"):
            out.append(f"({own_duplicates} of the messages repeat an earlier seq of their key)")
        if self.taken_before(own_duplicates):
            out.append(f"WARNING: duplicate seq numbers: {self.duplicates}")
        return out


def _offline_main(args: argparse.Namespace, prefix: str, options: ReplayOptions) -> int:
    from service.recording.offline import replay_offline, write_result

    engine = _offline_engine(args, prefix)
    result = replay_offline(args.file, engine, prefix, options)
    if args.out:
        write_result(result, args.out)
    else:
        json.dump(result.to_json(), sys.stdout, indent=1, sort_keys=True)
        sys.stdout.write("\n")
    confirmed = sum(p["status"] == "confirmed" for ps in result.pairs for p in ps["pairs"])
    tracks = sum(t["status"] == "confirmed" for b in result.tracks for t in b["tracks"])
    rate = result.messages / result.wall_s if result.wall_s > 0 else 0.0
    print(
        f"offline replay of {args.file}: {result.messages} messages ({result.plots} plots) in "
        f"{result.wall_s:.2f} s ({rate:.0f} msg/s); {tracks} confirmed tracks, {confirmed} confirmed pairs"
        + (f" -> {args.out}" if args.out else ""),
        file=sys.stderr,
        flush=True,
    )
    if result.damage:
        print(f"WARNING: {result.damage}; replayed what it holds up to there", file=sys.stderr, flush=True)
    if getattr(args, "compare", False):
        from service.recording.offline import compare_with_recording

        cmp = compare_with_recording(result, args.file, prefix)
        verdict = "IDENTICAL" if cmp.identical else f"DIFFERENT ({len(cmp.differences)} differences)"
        print(
            f"compare with the recorded outputs: tracks {cmp.recorded_tracks} recorded / "
            f"{cmp.replayed_tracks} replayed, pairs {cmp.recorded_pairs} recorded / "
            f"{cmp.replayed_pairs} replayed: {verdict}",
            file=sys.stderr,
            flush=True,
        )
        for line in cmp.differences[:20]:
            print(f"  {line}", file=sys.stderr)
        if not cmp.identical:
            return 1
    return 0
