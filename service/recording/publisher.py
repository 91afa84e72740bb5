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
        self.publisher(message.key).put(message.payload)

    def publisher(self, key: str) -> Any:
        """The key's publisher, declared at its first use."""
        publisher = self._publishers.get(key)
        if publisher is None:
            publisher = self._session.declare_publisher(
                key,
                encoding=zenoh.Encoding.APPLICATION_JSON,
                congestion_control=zenoh.CongestionControl.BLOCK,
                reliability=zenoh.Reliability.RELIABLE,
            )
            self._publishers[key] = publisher
        return publisher

    def forget(self, key: str) -> None:
        """Undeclare the key's publisher, if any (a source that goes away for good)."""
        publisher = self._publishers.pop(key, None)
        if publisher is not None:
            with contextlib.suppress(Exception):  # session already closed: nothing to undeclare
                publisher.undeclare()

    def close(self) -> None:
        for key in list(self._publishers):
            self.forget(key)

    def __enter__(self) -> ZenohReplayPublisher:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()
