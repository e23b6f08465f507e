"""Offline tools for MCAP logs: read with timing, export to JSON for Foxglove, inspect, repair.

A log is one MCAP file (a journal segment or a `derl record` output) or a run directory, whose
``journal/segment-NNNN.mcap`` files are read in order. Every reader goes through the journal's
tolerant record reader (`nodes.journal.segments`), so a truncated or corrupt file gives back the
messages before the damage instead of nothing. `info` says how healthy a file is; `repair` rewrites
a damaged one into a clean, indexed, zstd-compressed copy with `nodes.journal.segments.compact`;
`export_json` writes a ``json`` + ``jsonschema`` copy, the encodings Foxglove decodes (it cannot
decode msgpack: docs/bus.md).
"""

from __future__ import annotations

import base64
import importlib.util
import json
import logging
import math
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Literal, overload

from mcap.reader import make_reader
from mcap.records import Channel, Footer, Message, Schema
from mcap.well_known import MessageEncoding, SchemaEncoding
from mcap.writer import CompressionType, Writer

from derl.messages import MESSAGE_TYPES, DecodeError, MessageBase, decode
from derl.nodes.journal.reader import JournalDamaged, records
from derl.nodes.journal.segments import Logged, compact, is_mcap, read_logged, segments
from derl.nodes.tools.viewer_schema import viewer_schema

log = logging.getLogger("derl.mcap")

EXPORT_LIBRARY = "derl-export"


class LogError(ValueError):
    """A path that is not a readable log; the text says why."""


class NoLog(LogError):
    """A path where there is nothing (a usage error)."""


def log_files(path: Path) -> list[Path]:
    """The MCAP files of a log: the file itself, or a run directory's segments in order."""
    path = Path(path)
    if path.is_dir():
        files = segments(path)
        if not files:
            raise LogError(f"{path} holds no journal/segment-NNNN.mcap")
        return files
    if not path.is_file():
        raise NoLog(f"{path}: no such file")
    if not is_mcap(path):
        raise LogError(f"{path} is not an MCAP file")
    return [path]


def read_log(path: Path) -> Iterator[Logged]:
    """Every valid message of a log in file order; undecodable ones are logged and skipped."""
    for file in log_files(path):
        yield from read_logged(file)


# --- JSON ------------------------------------------------------------------------------------


@overload
def json_data(value: dict, binary: Callable[[bytes], object]) -> dict[str, object]: ...


@overload
def json_data(value: object, binary: Callable[[bytes], object]) -> object: ...


def json_data(value: object, binary: Callable[[bytes], object]) -> object:
    """`value` (dicts, sequences, scalars, bytes) as JSON data: `binary` turns bytes into JSON,
    NaN and infinities become null, map keys text, anything else its repr."""
    if isinstance(value, dict):
        return {str(key): json_data(item, binary) for key, item in value.items()}
    if isinstance(value, list | tuple):
        return [json_data(item, binary) for item in value]
    if isinstance(value, bytes):
        return binary(value)
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value if isinstance(value, str | int | float | bool | None) else repr(value)


def json_form(msg: MessageBase, binary: Callable[[bytes], object]) -> dict[str, object]:
    """`msg` as JSON data (see `json_data`)."""
    return json_data(msg.model_dump(mode="python"), binary)


def summarise_bytes(data: bytes) -> dict[str, int]:
    """How `derl topic echo` shows a bytes field (a policy checkpoint is about 1 MB)."""
    return {"bytes": len(data)}


def base64_text(data: bytes) -> str:
    return base64.b64encode(data).decode("ascii")


def json_schema(message_type: str) -> dict[str, object]:
    """The message type's JSON schema in the form Foxglove and Lichtblick read
    (`nodes.tools.viewer_schema`: references inlined, bytes as base64 strings)."""
    return viewer_schema(MESSAGE_TYPES[message_type])


def export_json(source: Path, out: Path) -> int:
    """Write every message of `source` to a new MCAP `out` as JSON; the number written.

    Same topics and times as the source; one schema per message type (its JSON schema, encoding
    ``jsonschema``), messages ``json`` with bytes in base64; chunked, indexed, zstd-compressed
    when the ``zstandard`` package is there.
    """
    files = log_files(source)  # a bad source fails before `out` is created
    compression = (
        CompressionType.ZSTD if importlib.util.find_spec("zstandard") else CompressionType.NONE
    )
    schemas: dict[str, int] = {}
    channels: dict[tuple[str, str], int] = {}
    written = 0
    with Path(out).open("xb") as f:
        writer = Writer(f, compression=compression)
        writer.start(profile="", library=EXPORT_LIBRARY)
        for file in files:
            for logged in read_log(file):
                kind = logged.message.type
                if kind not in schemas:
                    schemas[kind] = writer.register_schema(
                        kind, SchemaEncoding.JSONSchema, json.dumps(json_schema(kind)).encode()
                    )
                channel = channels.get((logged.topic, kind))
                if channel is None:
                    channel = writer.register_channel(
                        logged.topic, MessageEncoding.JSON, schemas[kind]
                    )
                    channels[(logged.topic, kind)] = channel
                data = json.dumps(json_form(logged.message, base64_text), allow_nan=False)
                writer.add_message(
                    channel,
                    log_time=logged.log_time,
                    data=data.encode(),
                    publish_time=logged.publish_time,
                    sequence=written & 0xFFFF_FFFF,
                )
                written += 1
        writer.finish()
    return written


# --- info and repair -------------------------------------------------------------------------

Integrity = Literal["clean", "recovered", "truncated", "corrupt"]
HEALTHY: frozenset[Integrity] = frozenset({"clean", "recovered"})  # nothing to repair


@dataclass
class ChannelInfo:
    topic: str
    schema: str
    encoding: str
    count: int = 0


@dataclass
class FileInfo:
    """What `derl log info` says about one MCAP file."""

    path: str
    size: int
    integrity: Integrity = "clean"
    detail: str = ""
    indexed: bool = False
    compression: list[str] = field(default_factory=list)
    messages: int = 0
    undecodable: int = 0
    start_ns: int | None = None
    end_ns: int | None = None
    channels: list[ChannelInfo] = field(default_factory=list)

    @property
    def span_s(self) -> float:
        if self.start_ns is None or self.end_ns is None:
            return 0.0
        return (self.end_ns - self.start_ns) / 1e9


def info(path: Path) -> list[FileInfo]:
    """Channels, counts, time span and integrity of every file of a log."""
    return [_file_info(file) for file in log_files(path)]


def _resumed_after(path: Path) -> bool:
    """Whether `path` is a journal segment of a run directory with a later segment: the run
    went on after it (a coordinator that restarts opens a new segment)."""
    if path.parent.name != "journal":
        return False
    names = [segment.name for segment in segments(path.parent.parent)]
    return path.name in names and names.index(path.name) < len(names) - 1


def _file_info(path: Path) -> FileInfo:
    result = FileInfo(path=str(path), size=path.stat().st_size)
    schemas: dict[int, str] = {}
    channels: dict[int, ChannelInfo] = {}
    footer = False
    damages: list[JournalDamaged] = []  # what is cut or corrupt, in file order
    before: int | None = None  # messages before the first damage
    for record in records(path, "skip", damages):
        if damages and before is None:
            before = result.messages
        _count(record, result, schemas, channels)
        footer = footer or isinstance(record, Footer)
    before = result.messages if before is None else before
    result.channels = list(channels.values())
    summary_count, summary_error = _summary(path, result)
    n = result.messages
    journal = path.parent.name == "journal"
    inside = next((d for d in damages if not d.torn_tail), None)  # damage with records after it
    of = "" if summary_count is None else f" of {summary_count}"
    if inside is not None:
        result.integrity = "corrupt"
        result.detail = (
            f"damaged at byte {inside.end} of {inside.size} ({type(inside.reason).__name__}), "
            f"and whole records follow from byte {inside.resumes}: damage, not the torn tail a "
            f"crash leaves at the end{'; the coordinator will not resume from it' * journal}; "
            f"{before} messages before the damage, {n}{of} readable in all"
        )
    elif footer and summary_count in (None, n):
        result.integrity = "clean"
        result.detail = "complete" if result.indexed else "complete, no index"
    elif footer or summary_count is not None:
        result.integrity = "corrupt"
        result.detail = f"{n} of {summary_count} messages readable (CRC or record)"
    elif _resumed_after(path):  # a coordinator died while writing it and its run resumed
        if not damages:  # (a torn tail is cut when the run resumes)
            result.integrity = "recovered"
            result.detail = (
                f"no footer: its writer died between messages (a crash) and the run went on in "
                f"the next segment; every record whole, {n} messages"
            )
        else:
            damage = damages[0]
            result.integrity = "corrupt"
            result.detail = (
                f"damaged at byte {damage.end} of {damage.size} ({type(damage.reason).__name__}), "
                f"not at the end of the run: the coordinator will not resume from it; {n} messages "
                "before the damage"
            )
    else:
        result.integrity = "truncated"
        torn = ""
        if damages:
            resumes = "; resuming the run cuts it" if journal else ""
            torn = f", then a torn tail of {damages[0].size - damages[0].end} bytes{resumes}"
        result.detail = (
            f"no footer ({summary_error}): the writer died or is still writing; {n} messages "
            f"recovered{torn}"
        )
    return result


def _count(
    record: object, result: FileInfo, schemas: dict[int, str], channels: dict[int, ChannelInfo]
) -> None:
    """Fold one record into `result` (channels, counts, times, undecodable messages)."""
    if isinstance(record, Schema):
        schemas[record.id] = record.name
    elif isinstance(record, Channel) and record.id not in channels:  # again in the summary
        channels[record.id] = ChannelInfo(
            record.topic, schemas.get(record.schema_id, ""), record.message_encoding
        )
    elif isinstance(record, Message) and record.channel_id in channels:
        channel = channels[record.channel_id]
        channel.count += 1
        result.messages += 1
        if result.start_ns is None or result.end_ns is None:
            result.start_ns = result.end_ns = record.log_time
        result.start_ns = min(result.start_ns, record.log_time)
        result.end_ns = max(result.end_ns, record.log_time)
        if channel.encoding == MessageEncoding.MessagePack:
            try:
                decode(record.data)
            except DecodeError:
                result.undecodable += 1


def _summary(path: Path, result: FileInfo) -> tuple[int | None, str]:
    """The message count the summary section gives (None without one) and why it is missing."""
    try:
        with path.open("rb") as f:
            summary = make_reader(f).get_summary()
    except Exception as error:  # the seeking reader fails in many ways on a damaged file
        return None, type(error).__name__
    if summary is None:
        return None, "no summary"
    result.indexed = bool(summary.chunk_indexes)
    result.compression = sorted({c.compression or "none" for c in summary.chunk_indexes})
    count = summary.statistics.message_count if summary.statistics else None
    return count, ""


def describe(files: list[FileInfo]) -> str:
    """The text form of `info`."""
    lines: list[str] = []
    for file in files:
        rate = file.messages / file.span_s if file.span_s else 0.0
        lines += [
            f"file:        {file.path} ({file.size:,} bytes)",
            f"integrity:   {file.integrity}: {file.detail}",
            f"indexed:     {'yes' if file.indexed else 'no'}"
            + (f" (chunks: {', '.join(file.compression)})" if file.compression else ""),
            f"messages:    {file.messages:,} ({rate:.1f}/s), undecodable: {file.undecodable}",
            f"time span:   {file.span_s:.3f} s" + _clock(file),
            "channels:",
        ]
        width = max((len(c.topic) for c in file.channels), default=5)
        lines += [
            f"  {c.topic:<{width}}  {c.schema:<18} {c.encoding:<8} {c.count:>8,}"
            for c in sorted(file.channels, key=lambda c: (c.topic, c.schema))
        ]
        if file.integrity not in HEALTHY:
            lines.append(f"repair with: derl log repair {file.path} OUT.mcap")
        lines.append("")
    segments_note = f"{len(files)} files, " if len(files) > 1 else ""
    totals = Counter(f.integrity for f in files)
    lines.append(
        f"total: {segments_note}{sum(f.messages for f in files):,} messages; "
        + ", ".join(f"{n} {state}" for state, n in sorted(totals.items()))
    )
    return "\n".join(lines)


def _clock(file: FileInfo) -> str:
    if file.start_ns is None or file.end_ns is None:
        return ""

    def at(ns: int) -> str:
        return datetime.fromtimestamp(ns / 1e9, UTC).strftime("%Y-%m-%d %H:%M:%S")

    return f" ({at(file.start_ns)} to {at(file.end_ns)} UTC)"


def repair(source: Path, out: Path) -> FileInfo:
    """Copy what can be read of a damaged file into a new clean, indexed file `out`."""
    if Path(source).is_dir():
        raise LogError(f"{source}: repair takes one file (a run directory's segments one by one)")
    (file,) = log_files(source)
    out = Path(out)
    if out.exists():
        raise LogError(f"{out} exists; choose another name")
    if not compact(file, out):
        raise LogError("repair needs the zstandard package (pip install zstandard)")
    return _file_info(out)
