"""Publishing replayed messages on Zenoh: one publisher per key, reliable, blocking.

``CongestionControl.BLOCK`` with ``Reliability.RELIABLE`` makes a slow receiver slow the
replay down instead of losing samples, which is what ``--speed 0`` relies on.
"""

from __future__ import annotations

import contextlib
from typing import Any

import zenoh

from service.recording.reader import RecordedMessage


class ZenohReplayPublisher:
    """Callable publishing each message's payload on its key with encoding application/json."""

    def __init__(self, session: zenoh.Session) -> None:
        self._session = session
        self._publishers: dict[str, Any] = {}

    def __call__(self, message: RecordedMessage) -> None:
        publisher = self._publishers.get(message.key)
        if publisher is None:
            publisher = self._session.declare_publisher(
                message.key,
                encoding=zenoh.Encoding.APPLICATION_JSON,
                congestion_control=zenoh.CongestionControl.BLOCK,
                reliability=zenoh.Reliability.RELIABLE,
            )
            self._publishers[message.key] = publisher
        publisher.put(message.payload)

    def close(self) -> None:
        for publisher in self._publishers.values():
            with contextlib.suppress(Exception):  # session already closed: nothing to undeclare
                publisher.undeclare()
        self._publishers.clear()

    def __enter__(self) -> ZenohReplayPublisher:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()
