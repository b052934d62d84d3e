"""MCAP logs of typed messages (the format rosbag2 and Foxglove use; docs/architecture.md section 4).

Layout written by :class:`LogWriter`:

* message encoding ``msgpack`` (the one-blob form of :func:`msgs.encode`), one channel per
  topic, channel metadata ``{"type": "RadarFrame"}``; msgpack is self-describing, so channels
  have no schema record (schema id 0, as the MCAP registry specifies for msgpack);
* radar configuration (chirp, virtual channels) and calibration as MCAP metadata records;
* crash safety: messages are written unchunked and flushed to the OS one by one, so a
  recorder killed at any instant leaves a valid prefix; only the summary and footer are
  missing. :class:`LogReader` reads such a file up to its last complete record and says so
  (``complete`` is False), and reads on past a damaged stretch in the middle of a file
  (``skipped``), as ``mcap recover`` does.

Times: ``log_time`` is when the recorder received the message and ``publish_time`` the same
wall-clock time (MCAP: "if not available, set to the log time"; the graph does not carry the
moment of publication, and a header's ``stamp_ns`` is sensor time, simulated in ``launch sim``, so
one clock per field); the sensor time stays in the message's own header. ``sequence`` is the
header's ``seq``. The player paces by ``log_time``.
"""

from __future__ import annotations

import io
import json
import mmap
import os
import struct
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import Channel, Message, Metadata
from mcap.writer import CompressionType, IndexType, Writer

from msgs.codec import decode, encode
from msgs.schema import MessageError, now_ns
from twinfocus.errors import TwinFocusError

MESSAGE_ENCODING = "msgpack"
_MAGIC = b"\x89MCAP0\r\n"


class LogWriter:
    """Append typed messages to a new MCAP file; :meth:`close` writes the summary and footer.

    Refuses to overwrite an existing file unless ``overwrite`` is set. The log is written beside
    the destination, in ``partial_path`` (``NAME.PID.partial``), and moved onto ``path`` by
    :meth:`close`: an earlier log at ``path`` is replaced only by a finished one, never by a
    failed run. A writer that is killed leaves ``partial_path`` (readable up to its last
    message, as every record is flushed) and the earlier log untouched. With
    ``keep_empty=False``, closing a log that holds no message deletes it and keeps the earlier one.
    """

    def __init__(
        self, path: str | os.PathLike, overwrite: bool = False, library: str = "twinfocus", keep_empty: bool = True
    ):
        self.path = Path(path)
        if self.path.is_dir():
            raise TwinFocusError(f"{self.path}: is a folder; give the log file's name")
        if self.path.exists() and not overwrite:
            raise TwinFocusError(f"{self.path}: already exists; choose another name or remove it first")
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self.partial_path = self.path.with_name(f"{self.path.name}.{os.getpid()}.partial")
            self._file = open(self.partial_path, "wb")
        except OSError as exc:
            raise TwinFocusError(f"{self.path}: cannot write there ({exc.strerror})") from None
        self.keep_empty = keep_empty
        self.kept: bool | None = None  # after close: whether the log was moved onto path
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
        t = log_time_ns or now_ns()
        self.write_blob(topic, msg.TYPE, encode(msg), t, t, msg.header.seq)

    def write_blob(
        self, topic: str, type_name: str, blob: bytes, log_time_ns: int, publish_time_ns: int, seq: int
    ) -> None:
        cid = self._channel(topic, type_name)
        self._writer.add_message(cid, int(log_time_ns), blob, max(0, int(publish_time_ns)), int(seq) & 0xFFFFFFFF)
        self._file.flush()
        self.counts[topic] = self.counts.get(topic, 0) + 1

    def write_encoded(
        self,
        topic: str,
        schema_name: str,
        schema_encoding: str,
        schema_data: bytes,
        message_encoding: str,
        data: bytes,
        log_time_ns: int,
        publish_time_ns: int = 0,
    ) -> None:
        """Append an already-encoded message of another encoding (e.g. Foxglove's protobuf
        schemas, nodes/foxglove_convert.py) on a channel with its own schema record; readers of
        this module skip such channels."""
        key = f"{topic}\0{message_encoding}"
        cid = self._channels.get(key)
        if cid is None:
            sid = self._writer.register_schema(schema_name, schema_encoding, schema_data)
            cid = self._writer.register_channel(topic, message_encoding, sid, {})
            self._channels[key] = cid
        self._writer.add_message(cid, int(log_time_ns), data, max(0, int(publish_time_ns)), 0)
        self._file.flush()
        self.counts[topic] = self.counts.get(topic, 0) + 1

    def add_metadata(self, name: str, values: dict[str, Any]) -> None:
        """A metadata record; values that are not strings are stored as JSON."""
        self._writer.add_metadata(name, {k: v if isinstance(v, str) else json.dumps(v) for k, v in values.items()})
        self._file.flush()

    def close(self, keep: bool = True) -> bool:
        """Finish the log and move it onto ``path``; returns whether it was moved. ``keep=False``
        (or an empty log with ``keep_empty=False``) deletes it and leaves ``path`` as it was."""
        if self.closed:
            return bool(self.kept)
        self.closed = True
        self._writer.finish()
        self._file.flush()
        os.fsync(self._file.fileno())
        self._file.close()
        self.kept = keep and (self.keep_empty or bool(self.counts))
        if self.kept:
            os.replace(self.partial_path, self.path)
        else:
            self.partial_path.unlink(missing_ok=True)
        return self.kept

    def __enter__(self) -> LogWriter:
        return self

    def __exit__(self, exc_type, *exc) -> None:
        # A failed block leaves its partial log beside the destination, not on it.
        if exc_type is None:
            self.close()
        elif not self.closed:
            self.closed = True
            self._file.close()


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


#: record types a log of this project holds, with how each is parsed (others are skipped)
_PARSED = {Opcode.CHANNEL: Channel, Opcode.MESSAGE: Message, Opcode.METADATA: Metadata}
_KNOWN_OPCODES = {int(op) for op in Opcode}


class LogReader:
    """Read an MCAP log: complete, cut short by a crash, or damaged in the middle.

    The records are found by walking their headers (opcode, length). Where the walk breaks (an
    unknown opcode, a length past the end, a message on a channel never declared, a record
    that does not parse) the reader searches forward for the next point where two records in a
    row are sound and goes on from there, as ``mcap recover`` goes on after a damaged chunk:
    a damaged stretch costs the messages in it, not everything after it.

    Attributes after construction (one pass over the file): ``complete`` (footer present and
    nothing skipped), ``valid_bytes`` (end of the last sound record), ``skipped`` (list of
    (offset, bytes) stretches skipped as damaged), ``channels`` (topic -> message type name),
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
            # Mapped, not read: the OS pages in what the walk touches; logs reach gigabytes.
            self._data = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
        self.channels: dict[str, str] = {}
        self.metadata: dict[str, dict] = {}
        self.counts: dict[str, int] = {}
        self.start_ns: int | None = None
        self.end_ns: int | None = None
        self.ordered = True
        self.skipped: list[tuple[int, int]] = []
        self._chans: dict[int, Channel] = {}
        self._index, footer = self._scan()
        self.valid_bytes = self._index[-1][1] + self._index[-1][2] if self._index else 8
        self.complete = footer and not self.skipped
        self.footer = footer
        for ch, rec in self._records():
            self.counts[ch.topic] = self.counts.get(ch.topic, 0) + 1
            self.start_ns = rec.log_time if self.start_ns is None else min(self.start_ns, rec.log_time)
            if self.end_ns is not None and rec.log_time < self.end_ns:
                self.ordered = False
            self.end_ns = rec.log_time if self.end_ns is None else max(self.end_ns, rec.log_time)

    @property
    def condition(self) -> str:
        """One line on the file's state ("" when it is complete)."""
        if self.complete:
            return ""
        parts = []
        if self.skipped:
            lost = sum(n for _, n in self.skipped)
            parts.append(
                f"damaged: skipped {lost} unreadable byte(s) in {len(self.skipped)} place(s), "
                f"first at offset {self.skipped[0][0]}; read the sound records around them"
            )
        if not self.footer:
            parts.append(f"not closed cleanly: read up to byte {self.valid_bytes} of {self.size}")
        return "; ".join(parts)

    def _record_at(self, pos: int):
        """(opcode, length, parsed record or None) of a sound record at ``pos``, else None."""
        d = self._data
        if pos + 9 > len(d):
            return None
        opcode, length = struct.unpack_from("<BQ", d, pos)
        if opcode not in _KNOWN_OPCODES or pos + 9 + length > len(d):
            return None
        cls = _PARSED.get(opcode)
        if cls is None:
            return opcode, length, None
        try:
            stream = ReadDataStream(io.BytesIO(d[pos + 9 : pos + 9 + length]))
            rec = cls.read(stream, length) if cls is Message else cls.read(stream)
        except Exception:  # any parse failure is damage
            return None
        if cls is not Message and stream.count != length:  # a record must fill its length exactly
            return None
        if isinstance(rec, Message) and rec.channel_id not in self._chans:
            return None
        return opcode, length, rec

    def _scan(self) -> tuple[list, bool]:
        """[(opcode, offset, record length incl. header, parsed)], footer found."""
        index = []
        pos = 8
        n = len(self._data)
        while pos < n:
            got = self._record_at(pos)
            if got is not None:
                opcode, length, rec = got
                if opcode == Opcode.FOOTER:
                    return index, self._data[pos + 9 + length : pos + 9 + length + 8] == _MAGIC
                if isinstance(rec, Channel):
                    self._chans[rec.id] = rec
                # Messages are parsed again when read: keeping their data would hold the log in memory.
                index.append((opcode, pos, 9 + length, None if isinstance(rec, Message) else rec))
                pos += 9 + length
                continue
            # Damage (or a truncated tail): find the next place where two sound records follow
            # each other (or one ends the file), and go on from there.
            start = pos
            pos = self._resync(pos + 1)
            if pos is None:
                if n - start > 0 and not self._tail_only(start):
                    self.skipped.append((start, n - start))
                return index, False
            self.skipped.append((start, pos - start))
        return index, False

    def _tail_only(self, start: int) -> bool:
        """A cut-short tail: the bytes from ``start`` are the beginning of one record."""
        d = self._data
        if start + 9 > len(d):
            return True
        opcode, length = struct.unpack_from("<BQ", d, start)
        return opcode in _KNOWN_OPCODES and start + 9 + length > len(d)

    def _resync(self, pos: int) -> int | None:
        d = self._data
        n = len(d)
        while pos + 9 <= n:
            first = self._record_at(pos)
            if first is not None and first[2] is not None:  # only parsed records anchor a resync
                nxt = pos + 9 + first[1]
                if nxt == n or self._record_at(nxt) is not None or self._tail_only(nxt):
                    return pos
            pos += 1
        return None

    def _records(self) -> Iterator[tuple[Channel, Message]]:
        """(channel, message record) pairs; channels and metadata are collected on the way."""
        for opcode, pos, size, rec in self._index:
            if opcode == Opcode.MESSAGE:
                rec = Message.read(ReadDataStream(io.BytesIO(self._data[pos + 9 : pos + size])), size - 9)
            if isinstance(rec, Channel):
                if rec.message_encoding == MESSAGE_ENCODING:  # e.g. Foxglove channels beside ours: not ours to read
                    self.channels.setdefault(rec.topic, rec.metadata.get("type", ""))
            elif isinstance(rec, Metadata):
                self.metadata.setdefault(rec.name, {k: _maybe_json(v) for k, v in rec.metadata.items()})
            elif isinstance(rec, Message):
                ch = self._chans[rec.channel_id]
                if ch.message_encoding != MESSAGE_ENCODING:
                    continue  # written by `record --foxglove` beside the msgpack channels
                yield ch, rec

    def messages(self, topics: Iterable[str] | None = None, start_ns: int | None = None) -> Iterator[LogMessage]:
        """Messages in file order (log-time order for files this project writes)."""
        wanted = set(topics) if topics else None
        for ch, rec in self._records():
            if wanted is not None and ch.topic not in wanted:
                continue
            if start_ns is not None and rec.log_time < start_ns:
                continue
            yield LogMessage(
                ch.topic, ch.metadata.get("type", ""), rec.log_time, rec.publish_time, rec.sequence, rec.data
            )


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
