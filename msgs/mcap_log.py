"""MCAP logs of typed messages (the format rosbag2 and Foxglove use; DESIGN.md section 4).

Layout written by :class:`LogWriter`:

* message encoding ``msgpack`` (the one-blob form of :func:`msgs.encode`), one channel per
  topic, channel metadata ``{"type": "RadarFrame"}``; msgpack is self-describing, so channels
  have no schema record (schema id 0, as the MCAP registry specifies for msgpack);
* radar configuration (chirp, virtual channels) and calibration as MCAP metadata records;
* crash safety: messages are written unchunked and flushed to the OS one by one, so a
  recorder killed at any instant leaves a valid prefix; only the summary and footer are
  missing. :class:`LogReader` reads such a file up to its last complete record and says so
  (``complete`` is False), like ``mcap recover`` would.

Times: ``log_time`` is when the recorder received the message, ``publish_time`` the header's
``stamp_ns``, ``sequence`` the header's ``seq``. The player paces by ``log_time``.
"""
from __future__ import annotations

import io
import json
import os
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Iterator

from mcap.exceptions import EndOfFile, McapError
from mcap.opcode import Opcode
from mcap.records import Channel, Footer, Message, Metadata
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, IndexType, Writer

from msgs.codec import decode, encode
from msgs.schema import MessageError, now_ns
from twinfocus.errors import TwinFocusError

MESSAGE_ENCODING = "msgpack"
_MAGIC = b"\x89MCAP0\r\n"


class LogWriter:
    """Append typed messages to a new MCAP file; :meth:`close` writes the summary and footer.

    Refuses to overwrite an existing file unless ``overwrite`` is set (a recording is written in
    place, never staged, so that a crash leaves what was recorded).
    """

    def __init__(self, path: str | os.PathLike, overwrite: bool = False, library: str = "twinfocus"):
        self.path = Path(path)
        if self.path.exists() and not overwrite:
            raise TwinFocusError(f"{self.path}: already exists; choose another name or remove it first")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = open(self.path, "wb")
        self._writer = Writer(
            self._file,
            use_chunking=False,  # every message is a top-level record: a killed writer loses nothing before it
            compression=CompressionType.NONE,
            index_types=IndexType.ATTACHMENT | IndexType.METADATA,
        )
        self._writer.start(profile="", library=library)
        self._file.flush()
        self._channels: dict[str, int] = {}
        self.counts: dict[str, int] = {}
        self.closed = False

    def _channel(self, topic: str, type_name: str) -> int:
        cid = self._channels.get(topic)
        if cid is None:
            cid = self._writer.register_channel(topic, MESSAGE_ENCODING, 0, {"type": type_name})
            self._channels[topic] = cid
        return cid

    def write(self, topic: str, msg: Any, log_time_ns: int | None = None) -> None:
        """Append ``msg`` on ``topic`` (log time: now unless given)."""
        self.write_blob(topic, msg.TYPE, encode(msg), log_time_ns or now_ns(), msg.header.stamp_ns, msg.header.seq)

    def write_blob(self, topic: str, type_name: str, blob: bytes, log_time_ns: int, publish_time_ns: int, seq: int) -> None:
        cid = self._channel(topic, type_name)
        # MCAP times are unsigned; a (simulated) stamp before the epoch keeps 0 here and its
        # exact value in the message's own header.
        self._writer.add_message(cid, int(log_time_ns), blob, max(0, int(publish_time_ns)), int(seq) & 0xFFFFFFFF)
        self._file.flush()
        self.counts[topic] = self.counts.get(topic, 0) + 1

    def add_metadata(self, name: str, values: dict[str, Any]) -> None:
        """A metadata record; values that are not strings are stored as JSON."""
        self._writer.add_metadata(name, {k: v if isinstance(v, str) else json.dumps(v) for k, v in values.items()})
        self._file.flush()

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        self._writer.finish()
        self._file.flush()
        os.fsync(self._file.fileno())
        self._file.close()

    def __enter__(self) -> "LogWriter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


@dataclass
class LogMessage:
    topic: str
    type_name: str
    log_time_ns: int
    publish_time_ns: int
    sequence: int
    blob: bytes

    def decode(self) -> Any:
        return decode(self.blob, where=f"{self.topic} @ log time {self.log_time_ns}")


class _Bounded(io.RawIOBase):
    """A read-only view of the first ``end`` bytes of a file."""

    def __init__(self, f, end: int):
        self._f = f
        self._end = end

    def readable(self) -> bool:
        return True

    def readinto(self, b) -> int:
        left = self._end - self._f.tell()
        if left <= 0:
            return 0
        n = min(len(b), left)
        data = self._f.read(n)
        b[: len(data)] = data
        return len(data)


class LogReader:
    """Read an MCAP log, complete or cut short by a crash.

    Attributes after construction (one pass over the file): ``complete`` (footer present),
    ``valid_bytes`` (length of the readable prefix), ``channels`` (topic -> message type name),
    ``metadata`` (name -> dict, JSON values decoded), ``counts`` (topic -> messages),
    ``start_ns`` / ``end_ns`` (first and last log time), ``ordered`` (log times non-decreasing).
    """

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        if not self.path.is_file():
            raise TwinFocusError(f"{self.path}: no such file")
        self.size = self.path.stat().st_size
        with open(self.path, "rb") as f:
            if f.read(8) != _MAGIC:
                raise TwinFocusError(f"{self.path}: not an MCAP file (bad magic bytes)")
            self.valid_bytes, self.complete = self._scan(f)
        self.channels: dict[str, str] = {}
        self.metadata: dict[str, dict] = {}
        self.counts: dict[str, int] = {}
        self.start_ns: int | None = None
        self.end_ns: int | None = None
        self.ordered = True
        for ch, rec in self._records():
            self.counts[ch.topic] = self.counts.get(ch.topic, 0) + 1
            self.start_ns = rec.log_time if self.start_ns is None else min(self.start_ns, rec.log_time)
            if self.end_ns is not None and rec.log_time < self.end_ns:
                self.ordered = False
            self.end_ns = rec.log_time if self.end_ns is None else max(self.end_ns, rec.log_time)

    def _scan(self, f) -> tuple[int, bool]:
        """Walk record headers: (end of the last complete record, whether a footer was found)."""
        pos = 8
        while True:
            f.seek(pos)
            head = f.read(9)
            if len(head) < 9:
                return pos, False
            opcode, length = struct.unpack("<BQ", head)
            end = pos + 9 + length
            if end > self.size:
                return pos, False
            if opcode == Opcode.FOOTER:
                f.seek(end)
                if f.read(8) == _MAGIC:
                    return self.size, True
                return pos, False
            pos = end

    def _records(self) -> Iterator[tuple[Channel, Message]]:
        """(channel, message record) pairs; channels and metadata are collected on the way."""
        with open(self.path, "rb") as f:
            stream = f if self.complete else _Bounded(f, self.valid_bytes)
            reader = StreamReader(stream, skip_magic=False, record_size_limit=None)
            chans: dict[int, Channel] = {}
            try:
                for rec in reader.records:
                    if isinstance(rec, Channel):
                        chans[rec.id] = rec
                        self.channels.setdefault(rec.topic, rec.metadata.get("type", ""))
                    elif isinstance(rec, Metadata):
                        self.metadata.setdefault(rec.name, {k: _maybe_json(v) for k, v in rec.metadata.items()})
                    elif isinstance(rec, Message):
                        ch = chans.get(rec.channel_id)
                        if ch is None:
                            raise TwinFocusError(f"{self.path}: message on unknown channel {rec.channel_id}")
                        if ch.message_encoding != MESSAGE_ENCODING:
                            raise TwinFocusError(
                                f"{self.path}: channel {ch.topic!r} uses message encoding {ch.message_encoding!r}, "
                                f"this reader only reads {MESSAGE_ENCODING!r}"
                            )
                        yield ch, rec
                    elif isinstance(rec, Footer):
                        return
            except EndOfFile:
                return  # the end of the readable prefix of a file cut short
            except McapError as exc:
                raise TwinFocusError(f"{self.path}: unreadable MCAP data ({exc})") from None

    def messages(self, topics: Iterable[str] | None = None, start_ns: int | None = None) -> Iterator[LogMessage]:
        """Messages in file order (log-time order for files this project writes)."""
        wanted = set(topics) if topics else None
        for ch, rec in self._records():
            if wanted is not None and ch.topic not in wanted:
                continue
            if start_ns is not None and rec.log_time < start_ns:
                continue
            yield LogMessage(ch.topic, ch.metadata.get("type", ""), rec.log_time, rec.publish_time, rec.sequence, rec.data)


def _maybe_json(v: str) -> Any:
    try:
        return json.loads(v)
    except (ValueError, TypeError):
        return v


def read_messages(path: str | os.PathLike, topics: Iterable[str] | None = None) -> list[tuple[str, Any]]:
    """All (topic, decoded message) pairs of a log, in order (small logs, tests)."""
    out = []
    for m in LogReader(path).messages(topics):
        try:
            out.append((m.topic, m.decode()))
        except MessageError as exc:
            raise TwinFocusError(f"{path}: {exc}") from None
    return out
