"""MCAP files read record by record, every chunk's CRC checked, and damage told from a torn tail.

`records` walks a file's records from its start without the summary (so a file cut at any byte
gives back every record before the cut) over a memory map, with `struct`: the `mcap` package's
stream reader reads byte by byte through Python calls and took 0.35 s of CPU for a paper run's
15 MB journal, a third of a restart's replay; this walk takes a few hundredths. It yields the
records derl reads (header, schemas, channels, messages, footer; a chunk's records once its CRC
is checked) as the `mcap` package's record types, and skips indexes, statistics, attachments and
metadata after checking that they fit.

A record that is cut, overruns its chunk, fails its CRC or has a reserved opcode is damage.
`JournalDamaged` says where the last whole record ends and where whole records start again (the
next chunk whose CRC is right, or a footer that ends the file), or that nothing whole follows:
a torn tail, the only damage a crash leaves, at the end of the file being written.
"""

from __future__ import annotations

import logging
import mmap
import struct
import zlib
from collections.abc import Iterator
from pathlib import Path
from typing import Literal

from mcap.exceptions import EndOfFile, InvalidMagic
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, DataEnd, Footer, Header, McapRecord, Message, Schema
from mcap.stream_reader import CRCValidationError
from mcap.writer import MCAP0_MAGIC

log = logging.getLogger(__name__)

Damage = Literal["skip", "tail", "raise"]
"""What a reader does at a record that is cut or corrupt: "skip" it (a warning) and read on from
the next whole record, if any; "tail": accept it only as a torn tail (nothing whole after it: the
end a crash leaves), else raise JournalDamaged; "raise": raise JournalDamaged."""


class JournalDamaged(RuntimeError):
    """A journal segment is damaged where a crash cannot have damaged it."""

    def __init__(
        self, path: Path, end: int, size: int, reason: object, resumes: int | None = None
    ) -> None:
        after = (
            ""
            if resumes is None
            else f", and whole records follow it from byte {resumes}: it is damage, not the torn "
            "tail a crash leaves at the end of the segment it was writing"
        )
        super().__init__(
            f"journal segment {path} is damaged at byte {end} of {size} ({_said(reason)})"
            f"{after}; the run cannot be resumed from it as it is. `derl log repair {path} "
            "REPAIRED.mcap` writes what can be read of it; move the damaged file away and put the "
            "repaired one in its place to resume without what was lost"
        )
        self.path, self.end, self.size, self.reason = path, end, size, reason
        self.resumes = resumes
        """Where whole records start again after the damage (None: nothing whole follows it, a
        torn tail)."""

    @property
    def why(self) -> str:
        """The damage in words."""
        return _said(self.reason)

    @property
    def torn_tail(self) -> bool:
        """Whether nothing whole follows the damage: the end a crash leaves."""
        return self.resumes is None


def _said(reason: object) -> str:
    return f"{type(reason).__name__}: {reason}" if str(reason) else type(reason).__name__


def records(
    path: Path, damage: Damage = "skip", found: list[JournalDamaged] | None = None
) -> Iterator[McapRecord]:
    """The records of an MCAP file in order; at a record that is cut or corrupt, `damage` says
    what happens, and each damage met is appended to `found` (else logged, if skipped)."""
    with path.open("rb") as f:
        size = f.seek(0, 2)
        if size == 0:
            return
        with mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as buf:
            start = 0
            while True:
                end = start  # where the last whole record ends
                try:
                    for end, record in _walk(buf, start):  # noqa: B007 (`end` is used below)
                        yield record
                    return
                except Exception as exc:  # cut, CRC, bad lengths or text, zstd...
                    damaged = JournalDamaged(path, end, size, exc, _whole_after(buf, end))
                if found is not None:
                    found.append(damaged)
                if damage == "raise" or (damage == "tail" and not damaged.torn_tail):
                    raise damaged
                if found is None and damaged.resumes is None:
                    log.warning("%s: broken tail skipped (bytes %d to %d): %s", path, end, size,
                                damaged.why)  # fmt: skip
                elif found is None:
                    log.warning("%s: damaged: bytes %d to %d skipped (%s), whole records "
                                "follow; `derl log repair` writes a clean copy", path, end,
                                damaged.resumes, damaged.why)  # fmt: skip
                if damaged.resumes is None:
                    return
                start = damaged.resumes


_HEAD = struct.Struct("<BQ")  # opcode, length
_U16, _U32, _U64 = struct.Struct("<H"), struct.Struct("<I"), struct.Struct("<Q")
_MESSAGE = struct.Struct("<HIQQ")  # channel, sequence, log time, publish time
_CHUNK = struct.Struct("<QQQI")  # start, end, uncompressed size, CRC
_FOOTER = struct.Struct("<QQI")  # summary start, summary offset start, summary CRC
_OWN = frozenset({Opcode.HEADER, Opcode.SCHEMA, Opcode.CHANNEL, Opcode.MESSAGE, Opcode.CHUNK,
                  Opcode.DATA_END, Opcode.FOOTER})  # fmt: skip


def _walk(buf: mmap.mmap, start: int) -> Iterator[tuple[int, McapRecord]]:
    """(where the record ends, the record) for each record from byte `start` (0: the file's
    start, its magic checked) up to the footer or the end; raises at the first damage."""
    size = len(buf)
    pos = start
    if start == 0:
        if buf[: len(MCAP0_MAGIC)] != MCAP0_MAGIC:
            raise EndOfFile() if size < len(MCAP0_MAGIC) else InvalidMagic(buf[:8])
        pos = len(MCAP0_MAGIC)
    while pos < size:
        opcode, end = _record(buf, pos, size)
        body = pos + _HEAD.size
        if opcode == Opcode.CHUNK:
            for record in _chunk_records(buf, body, end):
                yield end, record
        elif opcode == Opcode.DATA_END:
            (crc,) = _U32.unpack_from(buf, body)
            if start == 0 and crc != 0 and zlib.crc32(buf[:pos]) != crc:
                raise CRCValidationError(crc, zlib.crc32(buf[:pos]), DataEnd(crc))
        elif opcode == Opcode.FOOTER:
            footer = Footer(*_FOOTER.unpack_from(buf, body))
            if buf[end : end + len(MCAP0_MAGIC)] != MCAP0_MAGIC:
                raise EndOfFile("no magic after the footer")
            yield end + len(MCAP0_MAGIC), footer
            return
        else:
            parsed = _parse(opcode, buf, body, end)
            if parsed is not None:
                yield end, parsed
        pos = end


def _record(buf: bytes | mmap.mmap, pos: int, size: int) -> tuple[int, int]:
    """The opcode of the record at `pos` and where it ends (within `size`)."""
    if pos + _HEAD.size > size:
        raise EndOfFile(f"a record head cut at byte {pos}")
    opcode, length = _HEAD.unpack_from(buf, pos)
    end = pos + _HEAD.size + length
    if end > size:
        raise EndOfFile(f"a record of {length} bytes at byte {pos} cut at byte {size}")
    if opcode == 0:
        raise ValueError(f"reserved opcode 0 at byte {pos}")
    return opcode, end


def _chunk_records(buf: mmap.mmap, body: int, end: int) -> list[McapRecord]:
    """The records of the chunk record whose content is `buf[body:end]`, its CRC checked."""
    _, _, size, crc = _CHUNK.unpack_from(buf, body)
    compression, at = _text(buf, body + _CHUNK.size, end)
    (length,) = _U64.unpack_from(buf, at)
    if at + 8 + length != end:
        raise ValueError(f"a chunk's records of {length} bytes do not fill it")
    data = _decompressed(compression, buf[at + 8 : end], size)
    if crc != 0 and zlib.crc32(data) != crc:
        chunk = Chunk(compression, b"", 0, 0, crc, size)
        raise CRCValidationError(crc, zlib.crc32(data), chunk)
    out = []
    pos = 0
    while pos < len(data):
        opcode, inner_end = _record(data, pos, len(data))
        if opcode not in _OWN or opcode in (Opcode.CHUNK, Opcode.FOOTER, Opcode.DATA_END):
            raise ValueError(f"a record of opcode {opcode} inside a chunk")
        record = _parse(opcode, data, pos + _HEAD.size, inner_end)
        if record is not None:
            out.append(record)
        pos = inner_end
    return out


def _decompressed(compression: str, data: bytes, size: int) -> bytes:
    if compression == "":
        pass
    elif compression == "zstd":
        import zstandard

        data = zstandard.ZstdDecompressor().decompress(data, max_output_size=size)
    elif compression == "lz4":
        import lz4.frame

        data = lz4.frame.decompress(data)
    else:
        raise ValueError(f"unknown chunk compression {compression!r}")
    if len(data) != size:
        raise ValueError(f"a chunk of {len(data)} bytes, {size} announced")
    return data


def _parse(opcode: int, buf: bytes | mmap.mmap, pos: int, end: int) -> McapRecord | None:
    """The record of `opcode` whose content is `buf[pos:end]` (None: one derl skips)."""
    if opcode == Opcode.MESSAGE:
        _fits(pos + _MESSAGE.size, end)
        channel, sequence, log_time, publish_time = _MESSAGE.unpack_from(buf, pos)
        return Message(channel, log_time, buf[pos + _MESSAGE.size : end], publish_time, sequence)
    if opcode == Opcode.CHANNEL:
        (channel,) = _U16.unpack_from(buf, pos)
        (schema,) = _U16.unpack_from(buf, pos + 2)
        topic, at = _text(buf, pos + 4, end)
        encoding, at = _text(buf, at, end)
        (length,) = _U32.unpack_from(buf, at)
        at, stop = at + 4, at + 4 + length
        metadata = {}
        while at < stop:
            key, at = _text(buf, at, stop)
            metadata[key], at = _text(buf, at, stop)
        _fits(at, end)
        return Channel(channel, topic, encoding, metadata, schema)
    if opcode == Opcode.SCHEMA:
        (schema,) = _U16.unpack_from(buf, pos)
        name, at = _text(buf, pos + 2, end)
        encoding, at = _text(buf, at, end)
        (length,) = _U32.unpack_from(buf, at)
        _fits(at + 4 + length, end)
        return Schema(schema, buf[at + 4 : at + 4 + length], encoding, name)
    if opcode == Opcode.HEADER:
        profile, at = _text(buf, pos, end)
        library, at = _text(buf, at, end)
        return Header(profile, library)
    return None  # indexes, statistics, attachments, metadata, unknown records: skipped


def _text(buf: bytes | mmap.mmap, pos: int, end: int) -> tuple[str, int]:
    """The length-prefixed UTF-8 string at `pos` and where it ends (within `end`)."""
    (length,) = _U32.unpack_from(buf, pos)
    stop = pos + 4 + length
    _fits(stop, end)
    return bytes(buf[pos + 4 : stop]).decode(), stop


def _fits(stop: int, end: int) -> None:
    if stop > end:
        raise ValueError(f"a field overruns its record by {stop - end} bytes")


def _whole_after(buf: mmap.mmap, start: int) -> int | None:
    """Where the first whole chunk (its CRC right) after byte `start` begins, or the footer of
    a file that ends with one; None if there is neither (what follows `start` is a torn tail)."""
    size = len(buf)
    at = buf.find(bytes([Opcode.CHUNK]), start + 1)
    while at >= 0:
        try:
            _, end = _record(buf, at, size)
            _chunk_records(buf, at + _HEAD.size, end)
            return at
        except Exception:  # not a whole chunk
            pass
        at = buf.find(bytes([Opcode.CHUNK]), at + 1)
    footer = size - len(MCAP0_MAGIC) - _HEAD.size - _FOOTER.size
    if footer > start and buf[size - len(MCAP0_MAGIC) :] == MCAP0_MAGIC:
        opcode, length = _HEAD.unpack_from(buf, footer)
        if opcode == Opcode.FOOTER and length == _FOOTER.size:
            return footer
    return None
