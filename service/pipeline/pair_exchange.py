"""A pair's links between partitioned workers (``{prefix}/links/{a}/{b}``, ``PairLinks``): as
JSON, or as a frame whose ids and scores need no parsing.

Every worker takes every other worker's links for the cycle step, and worker 1 for the picture
too: about one message a pair per picture interval, each with a few hundred confirmed pairs.
Read by the model, a JSON message of 490 links costs about 120 µs, most of it the ids made into
lists and then into numpy arrays; as a frame (:mod:`service.wire.frames`) it is the header's
few fields and three :func:`numpy.frombuffer` views, about 20 µs.  The body holds the scores
(little-endian doubles), then each side's ids as fixed-width UTF-32LE (the form numpy keeps
strings in: each id ``widths[side]`` code points, padded with NUL), so the sender writes its
own arrays' bytes and the reader takes them as they are.  ``docs/contract.md``, "Scale-out".

A frame is read with the JSON form's rules (the ``PairLinks`` model's, for the header's
fields and the scores) and the layout's: ``binary`` names the three columns in this order,
``count`` the links, ``widths`` each side's characters an id (1 to :data:`MAX_ID_CHARS`), the
body is exactly their bytes, and every code point is a Unicode scalar value.  A trailing NUL of
an id is lost in that form (numpy strips it); such ids never occur (the sender's ids are numpy
strings already), and an id longer than :data:`MAX_ID_CHARS` goes as JSON.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from pydantic import ValidationError

from service.fusion.members import Links
from service.pipeline.decode import parse
from service.pipeline.errors import RejectionError
from service.pipeline.shared_links import SharedLinks
from service.wire.frames import decode_frame, encode_frame, is_frame
from service.wire.models import MAX_TRACKS, PairLinks, rejection_reason
from service.wire.outputs import encode

#: The columns of a links frame's body, in order.
LINK_COLUMNS = ["score", "track_a", "track_b"]
#: The longest id (characters) a frame carries; longer ones go as JSON.
MAX_ID_CHARS = 256
#: Unicode's code points end here; 0xD800-0xDFFF are surrogates, no characters of their own.
_CODE_POINTS_END = 0x110000
_SURROGATES = (0xD800, 0xE000)


def links_body(shared: SharedLinks) -> dict[str, Any]:
    """The ``PairLinks`` JSON body of a pair's links."""
    links = shared.links
    return {
        "source_a": links.source_a,
        "source_b": links.source_b,
        "time_s": shared.time_s,
        "release": shared.release,
        "track_a": links.track_a.tolist(),
        "track_b": links.track_b.tolist(),
        "score": links.score.tolist(),
    }


def links_frame(shared: SharedLinks) -> bytes:
    """The same message as a frame (the JSON bytes when an id is longer than
    :data:`MAX_ID_CHARS`)."""
    links = shared.links
    sides = [np.asarray(links.track_a, dtype=str), np.asarray(links.track_b, dtype=str)]
    widths = [max(side.dtype.itemsize // 4, 1) for side in sides]
    if max(widths) > MAX_ID_CHARS:
        return encode(links_body(shared))
    header = {
        "source_a": links.source_a,
        "source_b": links.source_b,
        "time_s": shared.time_s,
        "release": shared.release,
        "count": len(links.score),
        "widths": widths,
        "binary": LINK_COLUMNS,
    }
    body = [np.ascontiguousarray(links.score, dtype="<f8").tobytes()]
    body += [side.astype(f"<U{w}").tobytes() for side, w in zip(sides, widths, strict=True)]
    return encode_frame(header, b"".join(body))


def decode_links(payload: bytes, ids: tuple[str, str]) -> SharedLinks:
    """A ``PairLinks`` (JSON or a frame) on the key of the pair ``ids``, checked; a
    :class:`RejectionError` when it breaks a rule."""
    if is_frame(payload):
        got, track_a, track_b, score = _frame(payload, ids[0])
    else:
        got = parse(PairLinks, payload, ids[0])
        track_a, track_b = np.asarray(got.track_a, dtype=str), np.asarray(got.track_b, dtype=str)
        score = np.asarray(got.score, dtype=float)
    if sorted((got.source_a, got.source_b)) != sorted(ids):
        raise RejectionError("schema", f"sources {got.source_a}, {got.source_b} != key {ids}", ids[0])
    links = Links(got.source_a, got.source_b, track_a, track_b, score)
    return SharedLinks((ids[0], ids[1]), got.time_s, got.release, links)


def _fail(detail: str, source_id: str) -> RejectionError:
    return RejectionError("schema", f"links frame: {detail}", source_id)


def _frame(payload: bytes, source_id: str) -> tuple[PairLinks, np.ndarray, np.ndarray, np.ndarray]:
    """A frame's header fields (as the model, with empty columns) and its three columns."""
    try:
        header, data = decode_frame(payload)
    except ValueError as exc:
        raise _fail(str(exc), source_id) from None
    if not isinstance(header, dict):
        raise _fail("the header is not an object", source_id)
    if header.get("binary") != LINK_COLUMNS:
        raise _fail(f"binary must be {LINK_COLUMNS}", source_id)
    if any(name in header for name in LINK_COLUMNS):
        raise _fail("a binary column repeated in the header", source_id)
    n, widths = header.get("count"), header.get("widths")
    if type(n) is not int or not 0 <= n <= MAX_TRACKS:
        raise _fail(f"count must be an integer 0..{MAX_TRACKS}", source_id)
    if (
        not isinstance(widths, list)
        or len(widths) != 2
        or not all(type(w) is int and 1 <= w <= MAX_ID_CHARS for w in widths)
    ):
        raise _fail(f"widths must be two integers 1..{MAX_ID_CHARS}", source_id)
    try:  # the header's fields by the model's rules (its columns empty here)
        got = PairLinks.model_validate({**header, "track_a": [], "track_b": [], "score": []})
    except ValidationError as exc:
        reason, detail = rejection_reason(exc)
        raise RejectionError(reason, detail, source_id) from None
    size = n * (8 + 4 * widths[0] + 4 * widths[1])
    if len(data) != size:
        raise _fail(f"a body of {len(data)} bytes, {size} for {n} links", source_id)
    score = np.frombuffer(data, dtype="<f8", count=n).astype(float)
    if not np.all((score >= 0.0) & (score <= 1.0)):  # (NaN fails both)
        raise _fail("scores must be numbers in [0, 1]", source_id)
    units = np.frombuffer(data, dtype="<u4", offset=8 * n)
    if np.any(units >= _CODE_POINTS_END) or np.any((units >= _SURROGATES[0]) & (units < _SURROGATES[1])):
        raise _fail("ids must be UTF-32LE characters", source_id)
    track_a = np.frombuffer(data, dtype=f"<U{widths[0]}", count=n, offset=8 * n)
    track_b = np.frombuffer(data, dtype=f"<U{widths[1]}", count=n, offset=8 * n + 4 * widths[0] * n)
    return got, track_a, track_b, score
