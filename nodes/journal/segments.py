"""The coordinator's journal: the messages it accepts or sends, appended to MCAP segment files.

Coordinator state is a fold over this journal (docs/journal.md). A run directory holds
``journal/segment-0001.mcap``, ``segment-0002.mcap``, ... one per start: a crashed file cannot be
appended to. Each message type has its own channel (topic ``derl/<run>/<kind>``, message encoding
``msgpack``, schema encoding ``jsonschema`` with the model's JSON schema, schema name = type).

Durability (docs/journal.md): chunked, uncompressed, and ``Writer.flush()`` after every
message, which closes the chunk (its messages get their CRC) and flushes the file. A SIGKILL then
loses at most the message being written. A writer that handles messages in groups (the
coordinator) appends a group with ``flush=False``, flushes it once and has it synced (fsync)
before it publishes anything of the group: a crash, even a power loss, loses at most a group
nobody saw. Reading goes record by record without the summary, so a segment cut at any byte gives
back every message written before the cut (`nodes.journal.reader`). A crash can only leave a torn
tail: a bad record with nothing whole after it, at the end of the segment being written. A new
`Journal` first cuts that tail of the previous segment back to its last whole record; damage
anywhere else, a bad record with a whole chunk (its CRC right) or a footer after it included, is
`JournalDamaged` for the coordinator, never skipped; the tools skip it with a warning and read on
from the next whole chunk. A closed segment can be compacted into zstd chunks.
"""

from __future__ import annotations

import contextlib
import importlib.util
import json
import logging
import os
import re
import threading
import time
from collections import deque
from collections.abc import Iterator
from pathlib import Path
from types import TracebackType
from typing import NamedTuple

from mcap.records import Channel, Footer, Message, Schema
from mcap.well_known import MessageEncoding, SchemaEncoding
from mcap.writer import MCAP0_MAGIC, CompressionType, Writer

from derl.messages import (
    SCHEMA_VERSION,
    DecodeError,
    KeySpace,
    MessageBase,
    decode,
    encode,
    kind_of,
)
from derl.nodes.errors import REFUSED, DerlError
from derl.nodes.journal.reader import Damage, JournalDamaged, records
from derl.nodes.runtime.rundir import sync_folder

log = logging.getLogger(__name__)

LIBRARY = "derl-journal"
_SEGMENT = re.compile(r"segment-(\d+)\.mcap")


class JournalWriter:
    """One segment file, written message by message, each one (or group) flushed to the file."""

    def __init__(self, path: Path) -> None:
        self._lock = threading.Lock()
        self._closed = False
        self._open(Path(path))

    def _open(self, path: Path) -> None:
        """Start writing the new file `path` (its header in the file, its name on the disk)."""
        self.path = path
        self._file = self.path.open("xb")
        self._writer = Writer(self._file, compression=CompressionType.NONE)
        self._writer.start(profile="", library=LIBRARY)
        self._writer.flush()
        sync_folder(self.path.parent)  # else a power loss can lose the file, synced or not
        self._schemas: dict[str, int] = {}
        self._channels: dict[tuple[str, str], int] = {}
        self._sequence = 0
        self.pending = 0  # messages appended since the last flush

    def write(
        self,
        msg: MessageBase,
        publish_time_ns: int | None = None,
        data: bytes | None = None,
        flush: bool = True,
    ) -> None:
        """Append `msg` (log time now; publish time, e.g. the sender's, defaults to it);
        `data` is its encoding, if the caller has it already. Unless `flush` is False, it is in
        the file when this returns; else it is with the next `flush()`."""
        data = encode(msg) if data is None else data
        with self._lock:
            if self._closed:
                raise ValueError(f"{self.path} is closed")
            now = time.time_ns()
            self._add(msg, data, now, now if publish_time_ns is None else publish_time_ns, flush)

    def _add(self, msg: MessageBase, data: bytes, logged: int, published: int, flush: bool) -> None:
        """`write`'s work, the lock held."""
        self._append(msg, data, logged, published)
        if flush:
            self._writer.flush()
            self.pending = 0

    def _append(self, msg: MessageBase, data: bytes, log_time: int, publish_time: int) -> None:
        """Add `msg` to the chunk in progress (the lock held)."""
        self._writer.add_message(
            self._channel(msg),
            log_time=log_time,
            data=data,
            publish_time=publish_time,
            sequence=self._sequence & 0xFFFF_FFFF,
        )
        self.pending += 1
        self._sequence += 1

    def flush(self) -> None:
        """Close the chunk of the messages appended since the last flush and write it into the
        file (not yet onto the disk: `sync`)."""
        with self._lock:
            if not self._closed:
                self._writer.flush()
            self.pending = 0

    def sync(self) -> None:
        """Put what the file holds onto the disk (fsync); safe beside `write` and `flush` on
        another thread, and a no-op once closed (closing syncs)."""
        with self._lock:
            if self._closed:
                return
            fd = os.dup(self._file.fileno())
        try:
            os.fsync(fd)
        finally:
            os.close(fd)

    def _channel(self, msg: MessageBase) -> int:
        return channel_of(self._writer, self._schemas, self._channels, msg)

    def close(self) -> None:
        """Write the summary and footer and sync the file; closing twice is harmless."""
        with self._lock:
            if not self._closed:
                self._closed = True
                self._writer.finish()
                self._file.flush()
                os.fsync(self._file.fileno())
                self._file.close()

    def __enter__(self) -> JournalWriter:
        return self

    def __exit__(
        self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


def channel_of(
    writer: Writer,
    schemas: dict[str, int],
    channels: dict[tuple[str, str], int],
    msg: MessageBase,
) -> int:
    """The channel of `msg`'s type and run in `writer` (`schemas` by type, `channels` by type and
    run: what it registered so far), registered with its schema if new."""
    channel = channels.get((msg.type, msg.run))
    if channel is None:
        if msg.type not in schemas:
            schema = json.dumps(type(msg).model_json_schema()).encode()
            schemas[msg.type] = writer.register_schema(msg.type, SchemaEncoding.JSONSchema, schema)
        channel = writer.register_channel(
            _topic(msg),
            MessageEncoding.MessagePack,
            schemas[msg.type],
            {"schema_version": str(SCHEMA_VERSION)},
        )
        channels[(msg.type, msg.run)] = channel
    return channel


def segments(run_dir: Path) -> list[Path]:
    """The journal segments of a run directory, oldest first."""
    return [path for _, path in _numbered(run_dir)]


def _numbered(run_dir: Path) -> list[tuple[int, Path]]:
    folder = Path(run_dir) / "journal"
    if not folder.is_dir():
        return []
    matches = ((_SEGMENT.fullmatch(p.name), p) for p in folder.iterdir())
    return sorted((int(m[1]), p) for m, p in matches if m)


def replay(run_dir: Path) -> Iterator[MessageBase]:
    """Every message of every segment, in the order written; JournalDamaged for a segment
    that is cut or corrupt anywhere but at the tail of the last one."""
    paths = segments(run_dir)
    for k, path in enumerate(paths):
        last = k == len(paths) - 1
        mode: Damage = "tail" if last else "raise"
        yield from (logged.message for logged in read_logged(path, mode))


def cut_torn_tail(path: Path) -> int:
    """Cut a segment's torn tail (a record a crash left half written) back to its last whole
    record; the number of bytes cut (0 when the tail is whole). JournalDamaged, cutting nothing,
    if whole records follow the bad one: that is damage, not a torn tail."""
    try:
        last = deque(records(path, "raise"), maxlen=1)
    except JournalDamaged as damage:
        if not damage.torn_tail:
            raise
        with path.open("r+b") as f:
            f.truncate(damage.end)
            f.flush()
            os.fsync(f.fileno())
        log.warning("%s: torn tail recovered: %d bytes after byte %d cut (%s)", path,
                    damage.size - damage.end, damage.end, damage.why)  # fmt: skip
        return damage.size - damage.end
    if not (last and isinstance(last[0], Footer)):
        log.info("%s has no footer (its writer died between messages): every record whole", path)
    return 0


class Logged(NamedTuple):
    """One message of a log with its MCAP channel topic and times (ns since the epoch)."""

    topic: str
    log_time: int
    publish_time: int
    message: MessageBase


def is_mcap(path: Path) -> bool:
    """Whether the file starts with MCAP's magic bytes (else it is no log at all, not a
    damaged one)."""
    with Path(path).open("rb") as f:
        return f.read(len(MCAP0_MAGIC)) == MCAP0_MAGIC


def read_segment(path: Path) -> Iterator[MessageBase]:
    """The messages of one segment in file order; what does not decode is logged and skipped."""
    return (logged.message for logged in read_logged(path))


class OtherSchemaVersion(DerlError):
    """A log written with another version of the messages' schema: refused, not skipped (every
    message would be), as no restart or retry changes it."""

    code = REFUSED

    def __init__(self, path: Path, version: str) -> None:
        super().__init__(
            f"{path} was written with message schema version {version}, and this derl reads "
            f"version {SCHEMA_VERSION} only: read or resume it with the derl that wrote it "
            "(docs/protocol.md says what changed)"
        )


def read_logged(path: Path, damage: Damage = "skip") -> Iterator[Logged]:
    """The messages of one MCAP file in file order, with their topics and times; what a cut or
    corrupt file does is `damage`'s (see `records`). A message whose channel was lost with a
    damaged part is read all the same, on the topic the journal gives its type.
    `OtherSchemaVersion` for a channel that says another schema version (a journal or recording
    of another derl)."""
    channels: dict[int, Channel] = {}
    for record in records(path, damage):
        if isinstance(record, Channel):
            version = record.metadata.get("schema_version", "")
            if version.isdecimal() and version != str(SCHEMA_VERSION):  # (not bytes a crash left)
                raise OtherSchemaVersion(path, version)
            channels[record.id] = record
        elif isinstance(record, Message):
            channel = channels.get(record.channel_id)
            if channel is not None and channel.message_encoding != MessageEncoding.MessagePack:
                log.warning("%s: message %d on a non-msgpack channel skipped", path,
                            record.sequence)  # fmt: skip
                continue
            try:
                message = decode(record.data)
            except DecodeError as exc:
                topic = "an unknown channel" if channel is None else channel.topic
                log.warning("%s: message %d on %s skipped: %s", path, record.sequence, topic, exc)
                continue
            topic = _topic(message) if channel is None else channel.topic
            yield Logged(topic, record.log_time, record.publish_time, message)


def _topic(msg: MessageBase) -> str:
    """The channel topic the journal gives `msg`."""
    return KeySpace(msg.run).family(kind_of(msg))


class JournalFault(OSError):
    """The journal cannot be written (its file, and why): nothing after its last sync is on the
    disk, and nothing more is until `Journal.recover` succeeds."""

    def __init__(self, path: Path, error: OSError) -> None:
        why = error.strerror or str(error) or type(error).__name__
        super().__init__(error.errno, f"cannot write {path}: {why}")
        self.path, self.error = path, error


class Journal(JournalWriter):
    """A run's journal: writes the run's next segment; `replay` reads all of them.

    A write, flush or sync that fails (a full disk, an I/O error) does not raise where it
    happens: the journal keeps the messages written since its last sync in memory, writes
    nothing more, and `sync` raises the `JournalFault` (`failure`) until `recover` has cut the
    segment back to what was on the disk and written those messages into a new segment. An
    fsync that failed cannot be retried on the same file (Linux may drop the pages it could not
    write and report the next fsync as a success), so nothing unsynced is trusted to it."""

    def __init__(self, run_dir: Path) -> None:
        self.run_dir = Path(run_dir)
        folder = self.run_dir / "journal"
        if not folder.is_dir():  # a new run: its folder and the journal's, on the disk
            folder.mkdir(parents=True)
            sync_folder(self.run_dir.resolve().parent)
            sync_folder(self.run_dir)
        numbered = _numbered(self.run_dir)
        if numbered:
            cut_torn_tail(numbered[-1][1])
        super().__init__(self._next_segment())
        self.failure: JournalFault | None = None
        # (message, encoding, publish time) since the last sync; the first `_flushed` are in
        # the file; `_synced` bytes of the file are on the disk
        self._unsynced: list[tuple[MessageBase, bytes, int]] = []
        self._flushed = 0
        self._synced = self._flushed_size = self._sync_file()
        self._generation = 0  # segments started since the first (`recover`)

    def _next_segment(self) -> Path:
        number = max((n for n, _ in _numbered(self.run_dir)), default=0) + 1
        return self.run_dir / "journal" / f"segment-{number:04d}.mcap"

    def _sync_file(self) -> int:
        """The segment (all flushed into it) onto the disk: its size, which a failure can cut it
        back to."""
        os.fsync(self._file.fileno())
        return self._file.tell()

    @property
    def segment(self) -> Path:
        """The segment being written."""
        return self.path

    def replay(self) -> Iterator[MessageBase]:
        """Every message journaled in this run so far, this segment's included."""
        return replay(self.run_dir)

    def _add(self, msg: MessageBase, data: bytes, logged: int, published: int, flush: bool) -> None:
        """As `JournalWriter._add`, kept until synced; nothing written after a failure."""
        self._unsynced.append((msg, data, published))
        if self.failure is not None:
            return
        try:
            self._append(msg, data, logged, published)
            if flush:
                self._flush()
        except OSError as error:
            self._fail(error)

    def flush(self) -> None:
        with self._lock:
            if not self._closed and self.failure is None:
                try:
                    self._flush()
                except OSError as error:
                    self._fail(error)
            self.pending = 0

    def _flush(self) -> None:
        self._writer.flush()
        self.pending = 0
        self._flushed = len(self._unsynced)
        self._flushed_size = self._file.tell()  # a chunk over 1 MiB goes out before its flush

    def sync(self) -> None:
        """What was flushed into the file onto the disk; `JournalFault` if it is not (a failed
        write before, or this fsync)."""
        with self._lock:
            if self.failure is not None:
                raise self.failure
            if self._closed:
                return
            fd = os.dup(self._file.fileno())
            size, flushed, generation = self._flushed_size, self._flushed, self._generation
        try:
            os.fsync(fd)
        except OSError as error:
            with self._lock:
                if generation == self._generation:
                    raise self._fail(error) from None
            return  # an fsync of a segment `recover` replaced: its messages are in the new one
        finally:
            os.close(fd)
        with self._lock:
            if generation == self._generation:
                del self._unsynced[:flushed]
                self._flushed -= flushed
                self._synced = size

    def _fail(self, error: OSError) -> JournalFault:
        """Stop writing (the lock held): `error` is the journal's failure until `recover` (unless
        it has one already); that failure."""
        if self.failure is None:
            self.failure = JournalFault(self.path, error)
        return self.failure

    def recover(self) -> int | None:
        """After a failure: cut the failed segment back to what its last sync put on the disk,
        and write every message since into a new segment, synced; how many, or None if that did
        not work (`failure` says why, and nothing is left half done: a new segment that could
        not be written whole is removed)."""
        with self._lock:
            if self.failure is None:
                return 0
            failed, synced = self.path, self._synced
            with contextlib.suppress(OSError):  # what it could not write is cut below
                self._file.close()
            try:
                with failed.open("r+b") as f:
                    f.truncate(synced)
                    os.fsync(f.fileno())
                self._open(self._next_segment())
                for msg, data, published in self._unsynced:
                    self._append(msg, data, time.time_ns(), published)
                self._writer.flush()
                size = self._sync_file()
            except OSError as error:
                where = self.path
                self._discard_new(failed)
                self.failure = JournalFault(where, error)
                return None
            rewritten = len(self._unsynced)
            self._unsynced.clear()
            self._flushed, self._synced, self._flushed_size, self.pending = 0, size, size, 0
            self._generation += 1
            self.failure = None
            return rewritten

    def _discard_new(self, failed: Path) -> None:
        """Remove the new segment a failed `recover` started (the lock held), so that the
        failed one stays the last; the failed one is what it writes to again."""
        if self.path != failed:
            with contextlib.suppress(OSError):
                self._file.close()
            with contextlib.suppress(OSError):
                self.path.unlink()
                sync_folder(self.path.parent)
            self.path = failed

    def close(self) -> None:
        """As `JournalWriter.close`; a journal that failed, or fails to close, is cut back to
        what is on the disk (everything published is: the outbox syncs before it releases)."""
        if self.failure is None:
            try:
                super().close()
            except OSError as error:
                self.failure = JournalFault(self.path, error)
            else:
                return
        with self._lock:
            self._closed = True
            with contextlib.suppress(OSError):
                self._file.close()
            with contextlib.suppress(OSError), self.path.open("r+b") as f:
                f.truncate(self._synced)


def compact(segment: Path, out: Path | None = None) -> bool:
    """Rewrite a closed (or crashed) segment with 1 MiB zstd chunks and a summary, in place or
    into a new file `out`.

    Returns False, leaving the file as it is, when the `zstandard` package is missing. Never call
    it on the segment being written.
    """
    if importlib.util.find_spec("zstandard") is None:
        return False
    segment = Path(segment)
    target = segment if out is None else Path(out)
    tmp = target.with_name(target.name + ".tmp")
    schemas: dict[int, int] = {}
    channels: dict[int, int] = {}
    derived: tuple[dict[str, int], dict[tuple[str, str], int]] = ({}, {})  # for lost channels
    with tmp.open("wb") as f:
        writer = Writer(f, compression=CompressionType.ZSTD)
        writer.start(profile="", library=LIBRARY)
        for record in records(segment):
            if isinstance(record, Schema) and record.id not in schemas:
                schemas[record.id] = writer.register_schema(
                    record.name, record.encoding, record.data
                )
            elif isinstance(record, Channel) and record.id not in channels:
                channels[record.id] = writer.register_channel(
                    record.topic,
                    record.message_encoding,
                    schemas.get(record.schema_id, 0),
                    record.metadata,
                )
            elif isinstance(record, Message):
                channel = channels.get(record.channel_id)
                if channel is None:  # its channel was lost with a damaged part
                    try:
                        channel = channel_of(writer, *derived, decode(record.data))
                    except DecodeError:
                        continue
                writer.add_message(
                    channel,
                    log_time=record.log_time,
                    data=record.data,
                    publish_time=record.publish_time,
                    sequence=record.sequence,
                )
        writer.finish()
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, target)
    return True
