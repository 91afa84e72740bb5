"""What a recorded key is: its kind (:mod:`service.wire.keys`), its JSON Schema, key filters.

``{prefix}`` is matched literally so that a recording made under one prefix is read with the
same prefix it was made with.
"""

from __future__ import annotations

import json
from functools import lru_cache

import zenoh

from service.transport.session import zenoh_error_text
from service.wire.keys import MODEL_BY_KIND, KeyKind

#: MCAP schema encoding of a JSON Schema (MCAP well-known schema encodings).
SCHEMA_ENCODING = "jsonschema"
#: MCAP message encoding of every channel (contract §3).
MESSAGE_ENCODING = "json"


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
                raise ValueError(f"invalid key expression {expr!r}: {zenoh_error_text(exc)}") from None

    def matches(self, key: str) -> bool:
        if self._key_expr is None:
            return True
        return bool(self._key_expr.intersects(zenoh.KeyExpr(key)))


def key_lines(messages_by_key: dict[str, int], bytes_by_key: dict[str, int]) -> list[str]:
    """A report's per-key lines (recorder and replay alike): messages and bytes, keys aligned."""
    width = max((len(k) for k in messages_by_key), default=0)
    return [
        f"  {key:<{width}}  {messages_by_key[key]:>9} msgs  {bytes_by_key[key]:>12} bytes"
        for key in sorted(messages_by_key)
    ]
