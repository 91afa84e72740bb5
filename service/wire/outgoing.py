"""``Outgoing``: one message for the transport to publish, its payload encoded when first read."""

from __future__ import annotations

from collections.abc import Callable
from functools import cached_property
from typing import Any

from service.wire.outputs import encode


class Outgoing:
    """A message the transport should publish; its payload is encoded when first read.

    A transport with nobody listening on ``key`` never reads it, so unread outputs cost nothing.
    """

    def __init__(self, key: str, body: Callable[[], Any], encoded: Callable[[], bytes] | None = None) -> None:
        self.key = key
        #: The payload as a JSON-ready object, built when called.
        self.body = body
        #: The payload's bytes, when they are built another way than by encoding ``body``: the
        #: same bytes, sooner (:mod:`service.pipeline.payload_rows`), or the same message as a
        #: frame (:func:`service.pipeline.track_exchange.states_frame`).
        self._encoded = encoded

    @cached_property
    def payload(self) -> bytes:
        return self._encoded() if self._encoded is not None else encode(self.body())

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Outgoing) and (self.key, self.payload) == (other.key, other.payload)

    def __hash__(self) -> int:
        return hash((self.key, self.payload))

    def __repr__(self) -> str:
        return f"Outgoing({self.key!r})"
