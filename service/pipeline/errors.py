"""The one exception a stage raises for bad input: it becomes a ``Rejection`` on the wire."""

from __future__ import annotations

from service.wire.models import RejectionReason


class RejectionError(Exception):
    """An input message rejected whole, with the contract's reason and a human detail."""

    def __init__(self, reason: RejectionReason, detail: str, source_id: str | None = None) -> None:
        super().__init__(detail)
        self.reason: RejectionReason = reason
        self.detail = detail
        self.source_id = source_id


def unknown_radar(radar_id: str) -> RejectionError:
    """A radar's message before its site (contract: ``unknown_radar``)."""
    return RejectionError("unknown_radar", f"no site known for radar {radar_id!r}", radar_id)
