"""A journal or recording of the schema before this one, brought to this one (`derl log upgrade`).

Version 4 named the agent a message is about `child` (Tournament, TrainJob, TrainProgress,
FitnessReport, Ack, Reject, Birth, ChildFailed, Quarantine, Retrained) or `subject` (JobFailed);
version 5 names it `agent` and changes nothing else, so each version-4 message becomes a version-5
one with the same fields, checked as every message is. An upgraded file keeps every message's
times and order; a message that is not a valid version-4 one after all is dropped with a warning,
and the count says so. Older versions changed more than names (version 4's jobs carry the body a
version-3 job left its trainer to breed): they stay refused.
"""

from __future__ import annotations

import logging
import os
import shutil
from dataclasses import dataclass, replace
from pathlib import Path

import msgpack
from mcap.records import Channel, Message
from mcap.writer import CompressionType, Writer

from derl.messages import SCHEMA_VERSION, DecodeError, MessageBase, decode, encode
from derl.nodes.errors import DerlError
from derl.nodes.journal.reader import records
from derl.nodes.journal.segments import LIBRARY, channel_of, segments
from derl.nodes.runtime.rundir import sync_folder

log = logging.getLogger(__name__)

FROM_VERSION = 4
RENAMED = {"child": "agent", "subject": "agent"}
"""Version 4's field names that version 5 changed."""


def upgraded(payload: bytes) -> MessageBase:
    """The version-5 message of a version-4 `payload` (`DecodeError` if it is not one)."""
    try:
        raw = msgpack.unpackb(payload, use_list=False)
    except Exception as exc:  # msgpack raises many types for garbage
        raise DecodeError(f"not msgpack: {exc!r}") from exc
    if not isinstance(raw, dict) or raw.get("schema_version") != FROM_VERSION:
        raise DecodeError(f"not a version-{FROM_VERSION} message")
    fields = {RENAMED.get(key, key): value for key, value in raw.items()}
    fields["schema_version"] = SCHEMA_VERSION
    return decode(msgpack.packb(fields))


@dataclass(frozen=True)
class Upgraded:
    """What `upgrade` did to one file."""

    source: Path
    out: Path
    messages: int
    dropped: int


def upgrade(source: Path, out: Path) -> Upgraded:
    """Write the version-4 MCAP file `source` as a version-5 one, the new file `out` (synced);
    `DerlError` if `source` is of another version or `out` exists."""
    channels: dict[int, Channel] = {}
    for record in records(source):
        if isinstance(record, Channel):
            channels[record.id] = record
    versions = {c.metadata.get("schema_version") for c in channels.values()}
    if versions != {str(FROM_VERSION)}:
        found = ", ".join(sorted(str(v) for v in versions)) or "none"
        raise DerlError(
            f"{source} is not a journal or recording of schema version {FROM_VERSION} (its "
            f"channels say {found}): nothing to upgrade"
        )
    if out.exists():
        raise DerlError(f"{out} exists: choose a new file")
    written = dropped = 0
    schemas: dict[str, int] = {}
    by_type: dict[tuple[str, str], int] = {}
    with out.open("xb") as f:
        writer = Writer(f, compression=CompressionType.NONE)
        writer.start(profile="", library=LIBRARY)
        for record in records(source):
            if not isinstance(record, Message):
                continue
            try:
                msg = upgraded(record.data)
            except DecodeError as exc:
                log.warning("%s: message %d dropped: %s", source, record.sequence, exc)
                dropped += 1
                continue
            writer.add_message(
                channel_of(writer, schemas, by_type, msg),
                log_time=record.log_time,
                data=encode(msg),
                publish_time=record.publish_time,
                sequence=record.sequence,
            )
            written += 1
        writer.finish()
        f.flush()
        os.fsync(f.fileno())
    sync_folder(out.parent)
    return Upgraded(source, out, written, dropped)


def upgrade_run(run_dir: Path) -> list[Upgraded]:
    """Upgrade the journal of the run (or study) directory `run_dir` in place: its version-4
    segments are kept, as they were, in `journal.v4/`, and `journal/` holds their upgrade."""
    journal = run_dir / "journal"
    kept = run_dir / f"journal.v{FROM_VERSION}"
    old = segments(run_dir)
    if not old:
        raise DerlError(f"{run_dir} holds no journal (journal/segment-NNNN.mcap)")
    if kept.exists():
        raise DerlError(f"{kept} exists: an upgrade was started before; move it away first")
    new = run_dir / "journal.upgrading"
    shutil.rmtree(new, ignore_errors=True)
    new.mkdir()
    done = [upgrade(segment, new / segment.name) for segment in old]
    journal.rename(kept)  # from here on the old journal is only in journal.v4/ until ...
    new.rename(journal)  # ... this: each rename is atomic
    sync_folder(run_dir)
    return [replace(u, source=kept / u.source.name, out=journal / u.out.name) for u in done]
