"""Record Zenoh streams to MCAP and replay them (docs/contract.md §3), over Zenoh or offline.

Modules: :mod:`keys` (key kinds, schemas), :mod:`writer` (MCAP file), :mod:`recorder`
(subscriber -> queue -> writer thread), :mod:`reader` (any contract-shaped MCAP, damaged or
not), :mod:`replay` (selection, pacing, progress), :mod:`publisher` (Zenoh side),
:mod:`offline` (straight into an engine), :mod:`commands` (the two CLI entry points).
"""

from service.recording.commands import add_record_arguments, add_replay_arguments, record_main, replay_main
from service.recording.offline import OfflineResult, replay_offline, write_result
from service.recording.reader import (
    NotMcapError,
    NoUsableChannelError,
    RecordedMessage,
    RecordingError,
    RecordingReader,
)
from service.recording.recorder import Recorder, RecordReport, record
from service.recording.replay import ReplayOptions, ReplayReport, replay
from service.recording.writer import RecordingWriter

__all__ = [
    "NoUsableChannelError",
    "NotMcapError",
    "OfflineResult",
    "RecordReport",
    "RecordedMessage",
    "Recorder",
    "RecordingError",
    "RecordingReader",
    "RecordingWriter",
    "ReplayOptions",
    "ReplayReport",
    "add_record_arguments",
    "add_replay_arguments",
    "record",
    "record_main",
    "replay",
    "replay_main",
    "replay_offline",
    "write_result",
]
