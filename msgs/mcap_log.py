"""MCAP logs of typed messages (the format rosbag2 and Foxglove use; docs/architecture.md section 4).

Layout written by :class:`LogWriter`:

* message encoding ``msgpack`` (the one-blob form of :func:`msgs.encode`), one channel per
  topic, channel metadata ``{"type": "RadarFrame"}``; msgpack is self-describing, so channels
  have no schema record (schema id 0, as the MCAP registry specifies for msgpack);
* radar configuration (chirp, virtual channels) and calibration as MCAP metadata records;
* chunked and indexed: messages are grouped into chunks, each with the CRC-32 of its contents
  and followed by its message indexes; the summary holds the channels, statistics and chunk
  indexes, so ``mcap`` readers and Foxglove open the file indexed. A recording puts every
  message in a chunk of its own (``chunk_bytes=0``) and hands each chunk to the OS when it is
  complete: a writer killed at any instant loses at most the message it was writing, and
  damage costs the messages it hits, no more;
* written under a name that says it is partial (``NAME.partial-<UTC stamp>-<pid>.mcap`` beside
  ``NAME.mcap``) until :meth:`LogWriter.close` moves it onto its name: an earlier log is
  replaced only by a finished one.

:class:`LogReader` checks every chunk's CRC. A chunk that fails it, or a stretch of bytes that
does not parse, is skipped and described (:class:`Damage`: byte offset, topics and message
counts from the chunk's message indexes, log-time range); the sound records around it are read.
A file cut short by a crash reads up to its last complete record (``complete`` is False).

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
import time
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, Message, MessageIndex, Metadata
from mcap.stream_reader import breakup_chunk
from mcap.writer import CompressionType, IndexType, Writer

from msgs.codec import decode, encode
from msgs.schema import MessageError, now_ns
from twinfocus.errors import TwinFocusError

MESSAGE_ENCODING = "msgpack"
_MAGIC = b"\x89MCAP0\r\n"
_COMPRESSION = {"none": CompressionType.NONE, "zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4}


class LogWriteError(TwinFocusError):
    """Writing a log failed (a full disk, a lost device); the partial file has been deleted."""


def partial_path(path: str | os.PathLike, stamp: str | None = None, pid: int | None = None) -> Path:
    """Where a log bound for ``path`` is written until it is finished:
    ``DIR/STEM.partial-<YYYYmmddTHHMMSSZ>-<pid>SUFFIX`` (``graph.mcap`` ->
    ``graph.partial-20261126T140000Z-4242.mcap``)."""
    path = Path(path)
    stamp = stamp or time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
    return path.with_name(f"{path.stem}.partial-{stamp}-{os.getpid() if pid is None else pid}{path.suffix}")


class LogWriter:
    """Write typed messages to a new MCAP file, chunked and indexed; :meth:`close` finishes it.

    ``path``: the log's name; refused if it exists unless ``overwrite``. The file is written to
    :attr:`partial_path` and only :meth:`close` with ``keep=True`` moves it onto ``path``; a
    writer that is killed leaves ``partial_path`` (readable up to its last complete chunk) and
    the earlier log untouched. ``chunk_bytes``: 0 puts every message in a chunk of its own (a
    recording: a crash loses at most one message); otherwise chunks of about that many bytes
    (an export). ``compression``: "none", "zstd" or "lz4" per chunk. ``keep_empty=False``:
    a log that holds no message is never kept. A write that fails (``OSError``: a full disk)
    deletes the partial file and raises :class:`LogWriteError` naming the cause in one line.
    """

    def __init__(
        self,
        path: str | os.PathLike,
        overwrite: bool = False,
        library: str = "twinfocus",
        keep_empty: bool = True,
        chunk_bytes: int = 0,
        compression: str = "none",
    ):
        self.path = Path(path)
        if self.path.is_dir():
            raise TwinFocusError(f"{self.path}: is a folder; give the log file's name")
        if self.path.exists() and not overwrite:
            raise TwinFocusError(f"{self.path}: already exists; choose another name or remove it first")
        self.partial_path = partial_path(self.path)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._file = open(self.partial_path, "wb")
        except OSError as exc:
            raise TwinFocusError(f"{self.path}: cannot write there ({exc.strerror})") from None
        self.keep_empty = keep_empty
        self.chunk_bytes = max(0, int(chunk_bytes))
        self.kept: bool | None = None  # after close: whether the log was moved onto path
        self.where: Path | None = None  # after close: where the finished log is (None: deleted)
        self._writer = Writer(
            self._file,
            chunk_size=max(1, self.chunk_bytes),
            compression=_COMPRESSION[compression],
            index_types=IndexType.ALL,
            use_chunking=True,
        )
        self._channels: dict[str, int] = {}
        self._sequence: dict[int, int] = {}
        self.counts: dict[str, int] = {}
        self.closed = False
        with self._guard():
            self._writer.start(profile="", library=library)
            self._file.flush()

    @contextmanager
    def _guard(self) -> Iterator[None]:
        # A failed write (ENOSPC above all) must not leave a partial file filling the disk.
        try:
            yield
        except OSError as exc:
            self.discard()
            raise LogWriteError(
                f"{self.path}: {exc.strerror or exc} while writing the log; deleted its partial file "
                f"{self.partial_path.name}" + (f", the earlier {self.path.name} is kept" if self.path.exists() else "")
            ) from None

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
        """Append an encoded message (``blob``: :func:`msgs.encode`); ``seq`` is its header's."""
        with self._guard():
            cid = self._channel(topic, type_name)
            self._add(cid, int(log_time_ns), blob, int(publish_time_ns), int(seq))
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
        schemas, nodes/foxglove_convert.py) on a channel with its own schema record, numbered
        0, 1, 2, ... per channel (MCAP ``sequence``); readers of this module skip such channels."""
        key = f"{topic}\0{message_encoding}"
        with self._guard():
            cid = self._channels.get(key)
            if cid is None:
                sid = self._writer.register_schema(schema_name, schema_encoding, schema_data)
                cid = self._writer.register_channel(topic, message_encoding, sid, {})
                self._channels[key] = cid
            seq = self._sequence.get(cid, 0)
            self._sequence[cid] = seq + 1
            self._add(cid, int(log_time_ns), data, int(publish_time_ns), seq)
        self.counts[topic] = self.counts.get(topic, 0) + 1

    def _add(self, cid: int, log_time_ns: int, data: bytes, publish_time_ns: int, seq: int) -> None:
        self._writer.add_message(cid, log_time_ns, data, max(0, publish_time_ns), seq & 0xFFFFFFFF)
        if self.chunk_bytes == 0:
            self._writer.flush()  # the chunk of this one message, with its CRC and index, to the OS
        else:
            self._file.flush()

    def add_metadata(self, name: str, values: dict[str, Any]) -> None:
        """A metadata record; values that are not strings are stored as JSON."""
        with self._guard():
            self._writer.add_metadata(name, {k: v if isinstance(v, str) else json.dumps(v) for k, v in values.items()})
            self._file.flush()

    def close(self, keep: bool = True) -> Path | None:
        """Finish the log (summary, footer, fsync) and return where it now is: ``path`` with
        ``keep`` (the earlier log replaced), else ``partial_path``, finished, beside the earlier
        log; None when it held no message and ``keep_empty`` is False (deleted)."""
        if self.closed:
            return self.where
        if not self.keep_empty and not self.counts:
            self.discard()
            return None
        with self._guard():
            self._writer.finish()
            self._file.flush()
            os.fsync(self._file.fileno())
            self._file.close()
            self.closed = True
            self.kept = keep
            if keep:
                os.replace(self.partial_path, self.path)
        self.where = self.path if keep else self.partial_path
        return self.where

    def discard(self) -> None:
        """Stop writing and delete the partial file; ``path`` is left as it was."""
        self.closed = True
        self.kept = False
        try:
            self._file.close()
        except OSError:
            pass  # the buffered tail cannot be written (a full disk): it is being deleted anyway
        self.partial_path.unlink(missing_ok=True)

    def __enter__(self) -> LogWriter:
        return self

    def __exit__(self, exc_type, *exc) -> None:
        # A failed block leaves nothing: no partial file, the earlier log as it was.
        if exc_type is None:
            self.close()
        elif not self.closed:
            self.discard()


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


@dataclass
class Damage:
    """A stretch of a log that was skipped: ``offset`` and ``length`` in bytes, ``cause``,
    ``lost`` (topic -> messages, from the message indexes that follow a chunk; empty when
    unknown), the log-time range ``start_ns`` .. ``end_ns`` of what it held (None when
    unknown) and ``after_ns``, the log time of the last sound message before it."""

    offset: int
    length: int
    cause: str
    lost: dict[str, int] = field(default_factory=dict)
    start_ns: int | None = None
    end_ns: int | None = None
    after_ns: int | None = None  # log time of the last sound message before it
    channel_ids: dict[int, int] = field(default_factory=dict, repr=False)

    def describe(self, log_start_ns: int | None = None) -> str:
        """One clause: where, what it held, when (seconds into the log when its start is given)."""
        what = ", ".join(f"{t} ({n} message{'s' if n != 1 else ''})" for t, n in sorted(self.lost.items()))
        text = f"bytes {self.offset}-{self.offset + self.length} ({self.cause}): {what or 'topics unknown'}"
        t0 = log_start_ns or 0
        unit = " s into the log" if log_start_ns is not None else " s (log time)"
        if self.start_ns is not None and self.end_ns is not None:
            text += f", {(self.start_ns - t0) / 1e9:.3f}-{(self.end_ns - t0) / 1e9:.3f}{unit}"
        elif self.after_ns is not None:
            text += f", after {(self.after_ns - t0) / 1e9:.3f}{unit}"
        return text


#: record types a log of this project holds, with how each is parsed (others are skipped); Any:
#: mcap's record classes share no typed ``read`` (their base declares only ``write``)
_PARSED: dict[int, Any] = {
    Opcode.CHANNEL: Channel,
    Opcode.MESSAGE: Message,
    Opcode.METADATA: Metadata,
    Opcode.CHUNK: Chunk,
    Opcode.MESSAGE_INDEX: MessageIndex,
}
_KNOWN_OPCODES = {int(op) for op in Opcode}


class LogReader:
    """Read an MCAP log: complete, cut short by a crash, or damaged in the middle.

    The records are found by walking their headers (opcode, length); every chunk's contents are
    checked against its CRC-32. A chunk that fails the check is skipped; where the walk breaks
    (an unknown opcode, a length past the end, a record that does not parse) the reader
    searches forward for the next point where two records in a row are sound and goes on from
    there, as ``mcap recover`` does: damage costs the messages in it, not everything after it.
    Logs written unchunked (by earlier versions) read as before, without CRCs to check.

    Attributes after construction (one pass over the file): ``complete`` (footer present and
    nothing skipped), ``valid_bytes`` (end of the last sound record), ``damage`` (list of
    :class:`Damage`), ``skipped`` ((offset, bytes) of each), ``channels`` (topic -> message type
    name), ``metadata`` (name -> dict, JSON values decoded), ``counts`` (topic -> messages),
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
        self.damage: list[Damage] = []
        self.orphans = 0  # messages whose channel record was lost with a damaged chunk
        self._chans: dict[int, Channel] = {}
        self._chunked = False
        self._index, footer = self._scan()
        self.valid_bytes = self._index[-1][1] + self._index[-1][2] if self._index else 8
        self.footer = footer
        for ch, rec in self._records(count_orphans=True):
            self.counts[ch.topic] = self.counts.get(ch.topic, 0) + 1
            self.start_ns = rec.log_time if self.start_ns is None else min(self.start_ns, rec.log_time)
            if self.end_ns is not None and rec.log_time < self.end_ns:
                self.ordered = False
            self.end_ns = rec.log_time if self.end_ns is None else max(self.end_ns, rec.log_time)
        for d in self.damage:
            for cid, n in d.channel_ids.items():
                chan = self._chans.get(cid)
                topic = chan.topic if chan is not None else f"channel {cid}"
                d.lost[topic] = d.lost.get(topic, 0) + n
        self.complete = footer and not self.damage and not self.orphans

    @property
    def skipped(self) -> list[tuple[int, int]]:
        """(offset, bytes) of every damaged stretch skipped."""
        return [(d.offset, d.length) for d in self.damage]

    @property
    def condition(self) -> str:
        """One line on the file's state ("" when it is complete)."""
        if self.complete:
            return ""
        parts = []
        if self.damage:
            shown = "; ".join(d.describe(self.start_ns) for d in self.damage[:4])
            more = f"; and {len(self.damage) - 4} more" if len(self.damage) > 4 else ""
            parts.append(f"damaged, skipped {len(self.damage)} stretch(es): {shown}{more}")
        if self.orphans:
            parts.append(f"{self.orphans} message(s) skipped: their channel was declared in a damaged stretch")
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
        if cls is Message and self._chunked:
            return None  # a chunked log has no top-level messages: this is the inside of a damaged chunk
        if cls is Chunk and not _chunk_fits(d, pos, length):
            return None  # checked in place: copying a bogus length's worth of bytes would be slow
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
        """[(opcode, offset, record length incl. header, parsed or None)], footer found."""
        index: list[tuple[int, int, int, Any]] = []
        pos = 8
        n = len(self._data)
        open_damage: Damage | None = None  # message indexes right after it name what it held
        while pos < n:
            got = self._record_at(pos)
            if got is not None:
                opcode, length, rec = got
                if opcode == Opcode.FOOTER:
                    return index, self._data[pos + 9 + length : pos + 9 + length + 8] == _MAGIC
                if isinstance(rec, MessageIndex):
                    if open_damage is not None:
                        _note_index(open_damage, rec)
                    pos += 9 + length
                    continue
                open_damage = None
                if isinstance(rec, Chunk):
                    self._chunked = True
                    try:
                        inner = breakup_chunk(rec, validate_crc=True)
                    except Exception:  # a CRC mismatch, or contents that do not decompress or parse
                        open_damage = Damage(
                            pos, 9 + length, "fails its CRC", {}, rec.message_start_time, rec.message_end_time
                        )
                        self.damage.append(open_damage)
                        pos += 9 + length
                        continue
                    for r in inner:
                        if isinstance(r, Channel):
                            self._chans[r.id] = r
                    rec = None  # parsed again when read: keeping the data would hold the log in memory
                if isinstance(rec, Channel):
                    self._chans[rec.id] = rec
                # Messages are parsed again when read, for the same reason.
                index.append((opcode, pos, 9 + length, None if isinstance(rec, Message) else rec))
                pos += 9 + length
                continue
            # Damage (or a truncated tail): find the next place where two sound records follow
            # each other (or one ends the file), and go on from there.
            start = pos
            resumed = self._resync(pos + 1)
            if resumed is None:
                if n - start > 0 and not self._tail_only(start):
                    self.damage.append(self._unreadable(index, start, n - start))
                return index, False
            pos = resumed
            open_damage = self._unreadable(index, start, pos - start)
            self.damage.append(open_damage)
        return index, False

    def _unreadable(self, index: list, start: int, length: int) -> Damage:
        """A stretch that does not parse (what it held: from the message indexes after it, if any)."""
        d = Damage(start, length, "unreadable")
        for opcode, pos, _, _ in reversed(index):
            d.after_ns = self._log_time_at(opcode, pos)
            if d.after_ns is not None:
                break
        return d

    def _log_time_at(self, opcode: int, pos: int) -> int | None:
        if opcode == Opcode.MESSAGE:  # channel id u16, sequence u32, then log time u64
            return struct.unpack_from("<Q", self._data, pos + 9 + 6)[0]
        if opcode == Opcode.CHUNK:  # message start time u64, message end time u64
            return struct.unpack_from("<Q", self._data, pos + 9 + 8)[0]
        return None

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

    def _records(self, count_orphans: bool = False) -> Iterator[tuple[Channel, Message]]:
        """(channel, message record) pairs; channels and metadata are collected on the way."""
        for opcode, pos, size, rec in self._index:
            if opcode == Opcode.MESSAGE:
                rec = Message.read(ReadDataStream(io.BytesIO(self._data[pos + 9 : pos + size])), size - 9)
                recs = [rec]
            elif opcode == Opcode.CHUNK:
                chunk = Chunk.read(ReadDataStream(io.BytesIO(self._data[pos + 9 : pos + size])))
                recs = breakup_chunk(chunk, validate_crc=False)  # checked by the scan
            else:
                recs = [rec]
            for r in recs:
                if isinstance(r, Channel):
                    if r.message_encoding == MESSAGE_ENCODING:  # e.g. Foxglove channels beside ours: not ours to read
                        self.channels.setdefault(r.topic, r.metadata.get("type", ""))
                elif isinstance(r, Metadata):
                    self.metadata.setdefault(r.name, {k: _maybe_json(v) for k, v in r.metadata.items()})
                elif isinstance(r, Message):
                    ch = self._chans.get(r.channel_id)
                    if ch is None:
                        self.orphans += count_orphans
                        continue
                    if ch.message_encoding != MESSAGE_ENCODING:
                        continue  # written by `record --foxglove` beside the msgpack channels
                    yield ch, r

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


def _chunk_fits(d, pos: int, length: int) -> bool:
    """Whether the chunk header at ``pos`` accounts for exactly ``length`` bytes: start and end
    times, uncompressed size (u64 each), CRC (u32), compression (u32 length + text, short) and
    the data (u64 length + bytes)."""
    head = pos + 9 + 28
    if length < 40 or head + 4 > len(d):
        return False
    (clen,) = struct.unpack_from("<I", d, head)
    if clen > 16 or head + 4 + clen + 8 > len(d):
        return False
    (dlen,) = struct.unpack_from("<Q", d, head + 4 + clen)
    return 28 + 4 + clen + 8 + dlen == length


def _note_index(d: Damage, idx: MessageIndex) -> None:
    """Add what a message index says a damaged stretch held (channel, count, times)."""
    if not idx.records:
        return
    d.channel_ids[idx.channel_id] = d.channel_ids.get(idx.channel_id, 0) + len(idx.records)
    times = [t for t, _ in idx.records]
    d.start_ns = min(times) if d.start_ns is None else min(d.start_ns, min(times))
    d.end_ns = max(times) if d.end_ns is None else max(d.end_ns, max(times))


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
