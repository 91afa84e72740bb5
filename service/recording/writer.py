"""An MCAP file of Zenoh samples in the contract's shape (docs/contract.md §3).

One channel per key (topic = the key), ``message_encoding`` ``json``, the key's JSON Schema
where the key has a contract payload, payload bytes unchanged, ``log_time`` = receipt time and
``publish_time`` = the Zenoh timestamp (nanoseconds since the Unix epoch; the receipt time when
the sample has none, as the MCAP specification asks). Single-threaded: the recorder owns it
from its writer thread.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO

from mcap.writer import CompressionType, Writer

from service.recording.keys import MESSAGE_ENCODING, SCHEMA_ENCODING, schema_for_kind
from service.wire.keys import classify_key

#: Uncompressed bytes per MCAP chunk.  Smaller than the library's 1 MiB so that a recorder
#: killed without a chance to finish its file loses little (see also ``flush_interval_s``).
DEFAULT_CHUNK_BYTES = 256 * 1024
#: Header ``library`` field: who wrote the file.
LIBRARY = "topofusion-recorder"
#: MCAP metadata record naming the recording's parameters.
METADATA_NAME = "topofusion"


@dataclass
class KeyCount:
    messages: int = 0
    bytes: int = 0


@dataclass
class WriteTotals:
    """What a writer has written so far."""

    by_key: dict[str, KeyCount] = field(default_factory=dict)

    @property
    def messages(self) -> int:
        return sum(c.messages for c in self.by_key.values())

    @property
    def payload_bytes(self) -> int:
        return sum(c.bytes for c in self.by_key.values())


class RecordingWriter:
    """Writes samples to an MCAP file; call :meth:`close` (or use ``with``) to finish it.

    ``log_time`` is made non-decreasing (a wall-clock step backwards during a recording must
    not reorder samples on replay): file order is then log-time order.
    """

    def __init__(
        self,
        output: str | Path | BinaryIO,
        prefix: str = "fusion",
        *,
        chunk_bytes: int = DEFAULT_CHUNK_BYTES,
        compression: CompressionType = CompressionType.ZSTD,
        metadata: dict[str, str] | None = None,
    ) -> None:
        self.prefix = prefix
        self._own_stream = isinstance(output, (str, Path))
        if isinstance(output, (str, Path)):
            self._stream: BinaryIO = open(output, "wb")  # noqa: SIM115 - closed in close()
        else:
            self._stream = output
        self._writer = Writer(self._stream, chunk_size=chunk_bytes, compression=compression)
        self._writer.start(profile="", library=LIBRARY)
        meta = {"prefix": prefix, "created_unix_s": f"{time.time():.3f}"}
        meta.update(metadata or {})
        self._writer.add_metadata(METADATA_NAME, meta)
        self._stream.flush()  # the file is a recognisable MCAP from the first moment
        self._channels: dict[str, int] = {}
        self._schemas: dict[str, int] = {}
        self._sequence: dict[int, int] = {}
        self._last_log_time = 0
        self.totals = WriteTotals()
        self.closed = False

    def _channel_id(self, key: str) -> int:
        channel_id = self._channels.get(key)
        if channel_id is not None:
            return channel_id
        kind = classify_key(key, self.prefix)
        schema = schema_for_kind(kind)
        schema_id = 0
        if schema is not None:
            name, data = schema
            schema_id = self._schemas.get(name, 0)
            if not schema_id:
                schema_id = self._writer.register_schema(name=name, encoding=SCHEMA_ENCODING, data=data)
                self._schemas[name] = schema_id
        channel_id = self._writer.register_channel(
            topic=key, message_encoding=MESSAGE_ENCODING, schema_id=schema_id, metadata={"kind": kind}
        )
        self._channels[key] = channel_id
        self.totals.by_key[key] = KeyCount()
        return channel_id

    def write(self, key: str, payload: bytes, log_time_ns: int, publish_time_ns: int | None = None) -> None:
        """Append one sample; ``payload`` is written byte for byte."""
        channel_id = self._channel_id(key)
        log_time = max(int(log_time_ns), self._last_log_time)
        self._last_log_time = log_time
        sequence = self._sequence.get(channel_id, 0)
        self._sequence[channel_id] = sequence + 1
        self._writer.add_message(
            channel_id=channel_id,
            log_time=log_time,
            data=bytes(payload),
            publish_time=log_time if publish_time_ns is None else int(publish_time_ns),
            sequence=sequence & 0xFFFFFFFF,
        )
        count = self.totals.by_key[key]
        count.messages += 1
        count.bytes += len(payload)

    def flush(self) -> None:
        """Close the chunk in progress and push it to the OS, so a crash loses nothing before."""
        flush = getattr(self._writer, "flush", None)
        if flush is not None:  # mcap >= 1.2
            flush()
        else:
            self._stream.flush()

    def close(self) -> None:
        """Write the summary and footer; the file is then a complete, indexed MCAP."""
        if self.closed:
            return
        self.closed = True
        try:
            self._writer.finish()
            self._stream.flush()
        finally:
            if self._own_stream:
                self._stream.close()

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()
