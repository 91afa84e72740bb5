"""What a recorded key is: its kind (contract §1), its payload model and JSON Schema.

The key shapes are the contract's; ``{prefix}`` is matched literally so that a recording made
under one prefix is read with the same prefix it was made with.
"""

from __future__ import annotations

import json
import re
from functools import lru_cache
from typing import Literal

import zenoh
from pydantic import BaseModel

from service.messages import AisBatch, PairSet, PlotBatch, RadarSite, Rejection, Status, TrackBatch

KeyKind = Literal["site", "plots", "ais", "tracks", "pairs", "errors", "status", "other"]

#: Kinds the service consumes: replay republishes only these unless told to include all keys.
INPUT_KINDS: frozenset[KeyKind] = frozenset({"site", "plots", "ais"})
#: Kinds the service itself publishes.
OUTPUT_KINDS: frozenset[KeyKind] = frozenset({"tracks", "pairs", "errors", "status"})

#: Payload model per key kind (contract §1 table).
MODEL_BY_KIND: dict[KeyKind, type[BaseModel]] = {
    "site": RadarSite,
    "plots": PlotBatch,
    "ais": AisBatch,
    "tracks": TrackBatch,
    "pairs": PairSet,
    "errors": Rejection,
    "status": Status,
}

#: MCAP schema encoding of a JSON Schema (MCAP well-known schema encodings).
SCHEMA_ENCODING = "jsonschema"
#: MCAP message encoding of every channel (contract §3).
MESSAGE_ENCODING = "json"

_ID = r"[A-Za-z0-9_-]{1,64}"
_SHAPES: tuple[tuple[KeyKind, str], ...] = (
    ("site", rf"radar/{_ID}/site"),
    ("plots", rf"radar/{_ID}/plots"),
    ("tracks", rf"radar/{_ID}/tracks"),
    ("ais", rf"ais/{_ID}/reports"),
    ("pairs", rf"pairs/{_ID}/{_ID}"),
    ("errors", r"errors"),
    ("status", r"status"),
)


@lru_cache(maxsize=64)
def _patterns(prefix: str) -> tuple[tuple[KeyKind, re.Pattern[str]], ...]:
    head = re.escape(prefix.strip("/"))
    return tuple((kind, re.compile(rf"^{head}/{shape}$")) for kind, shape in _SHAPES)


def classify_key(key: str, prefix: str) -> KeyKind:
    """The contract kind of a concrete key under ``prefix``, ``"other"`` when it has none."""
    for kind, pattern in _patterns(prefix):
        if pattern.match(key):
            return kind
    return "other"


@lru_cache(maxsize=16)
def schema_for_kind(kind: KeyKind) -> tuple[str, bytes] | None:
    """``(name, JSON Schema bytes)`` of the payload model of ``kind``, or None for ``other``."""
    model = MODEL_BY_KIND.get(kind)
    if model is None:
        return None
    schema = model.model_json_schema()
    return model.__name__, json.dumps(schema, sort_keys=True, separators=(",", ":")).encode("utf-8")


def is_concrete_key(topic: str) -> bool:
    """Whether ``topic`` is a canonical Zenoh key without wildcards (publishable as is)."""
    if not topic or any(ch in topic for ch in "*$#?"):
        return False
    try:
        return str(zenoh.KeyExpr(topic)) == topic
    except Exception:  # zenoh raises ZError (a plain Exception) on an invalid key expression
        return False


class KeyFilter:
    """A Zenoh key expression (``--key``) matched against concrete keys; None matches all."""

    def __init__(self, expr: str | None) -> None:
        self.expr = expr
        self._key_expr: zenoh.KeyExpr | None = None
        if expr is not None:
            try:
                self._key_expr = zenoh.KeyExpr(expr)
            except Exception as exc:
                raise ValueError(f"invalid key expression {expr!r}: {exc}") from exc

    def matches(self, key: str) -> bool:
        if self._key_expr is None:
            return True
        return bool(self._key_expr.intersects(zenoh.KeyExpr(key)))
