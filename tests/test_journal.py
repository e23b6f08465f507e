"""The coordinator's MCAP journal on real files: replay, cut tails, kill -9, compaction."""

from __future__ import annotations

import errno
import json
import logging
import os
import random
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import msgpack
import pytest
from mcap.reader import make_reader
from mcap.records import Message
from mcap.stream_reader import StreamReader
from mcap.well_known import MessageEncoding, SchemaEncoding
from mcap.writer import CompressionType, Writer
from nodes_fixtures import FullDisk

from derl.evolution import load_profile
from derl.messages import (
    MESSAGE_TYPES,
    SCHEMA_VERSION,
    KeySpace,
    MessageBase,
    decode,
    encode,
    kind_of,
)
from derl.messages.examples import examples
from derl.nodes.coordinator.node import Coordinator
from derl.nodes.coordinator.run.rules import EvolutionRules
from derl.nodes.errors import REFUSED, DerlError
from derl.nodes.journal.segments import (
    Journal,
    JournalDamaged,
    JournalFault,
    JournalWriter,
    compact,
    read_logged,
    read_segment,
    records,
    replay,
    segments,
)


def mixed(count: int, start: int = 0) -> list[MessageBase]:
    """`count` messages cycling through every type, ids and numbers varying."""
    types = len(MESSAGE_TYPES)
    return [examples("run1", i // types)[i % types] for i in range(start, start + count)]


def payloads(msgs: list[MessageBase]) -> list[bytes]:
    return [encode(m) for m in msgs]


def closed_file(path: Path, written: list[bytes]) -> Path:
    """A closed journal file of the messages `written`, each flushed on its own."""
    with JournalWriter(path) as writer:
        for payload in written:
            writer.write(decode(payload))
    return path


def test_two_segments_replay_in_order(tmp_path: Path) -> None:
    written = mixed(1000)
    with Journal(tmp_path) as journal:
        assert journal.segment == tmp_path / "journal" / "segment-0001.mcap"
        for msg in written[:500]:
            journal.write(msg)
    with Journal(tmp_path) as journal:
        assert journal.segment.name == "segment-0002.mcap"
        assert payloads(list(journal.replay())) == payloads(written[:500])
        for msg in written[500:]:
            journal.write(msg)
    assert [p.name for p in segments(tmp_path)] == ["segment-0001.mcap", "segment-0002.mcap"]
    back = list(replay(tmp_path))
    assert back == written
    assert payloads(back) == payloads(written)


def test_standard_reader_sees_channels_schemas_and_encodings(tmp_path: Path) -> None:
    written = mixed(3 * len(MESSAGE_TYPES))
    with JournalWriter(tmp_path / "j.mcap") as writer:
        for i, msg in enumerate(written):
            writer.write(msg, publish_time_ns=1000 + i)
    with (tmp_path / "j.mcap").open("rb") as f:
        reader = make_reader(f, validate_crcs=True)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        assert summary.statistics.message_count == len(written)
        assert {c.compression for c in summary.chunk_indexes} == {""}
        schemas = summary.schemas
        assert sorted(s.name for s in schemas.values()) == sorted(MESSAGE_TYPES)
        for schema in schemas.values():
            assert schema.encoding == SchemaEncoding.JSONSchema == "jsonschema"
            assert json.loads(schema.data) == MESSAGE_TYPES[schema.name].model_json_schema()
        topics = {schemas[c.schema_id].name: c.topic for c in summary.channels.values()}
        assert len(summary.channels) == len(MESSAGE_TYPES)
        for msg in written:
            assert topics[msg.type] == KeySpace("run1").family(kind_of(msg))
        assert {c.message_encoding for c in summary.channels.values()} == {"msgpack"}
        read = list(reader.iter_messages(log_time_order=False))
    assert [decode(m.data) for _, _, m in read] == written
    assert [m.publish_time for _, _, m in read] == [1000 + i for i in range(len(written))]
    assert [m.sequence for _, _, m in read] == list(range(len(written)))
    assert all(m.log_time > 10**18 for _, _, m in read)  # ns since the epoch


def test_segment_cut_at_any_byte_gives_a_prefix(tmp_path: Path, caplog) -> None:
    written = payloads(mixed(60))
    full = tmp_path / "full.mcap"
    closed_file(full, written)
    data = full.read_bytes()
    rng = random.Random(7)
    cuts = sorted({0, 1, 8, 9, len(data) - 1, len(data), *rng.sample(range(len(data)), 30)})
    counts = []
    cut_file = tmp_path / "cut.mcap"
    for cut in cuts:
        cut_file.write_bytes(data[:cut])
        with caplog.at_level(logging.INFO, logger="derl.nodes.journal.segments"):
            back = payloads(list(read_segment(cut_file)))
        assert back == written[: len(back)], cut
        counts.append(len(back))
    assert counts == sorted(counts)
    assert counts[-1] == counts[-2] == len(written)  # the summary adds nothing to lose
    assert counts[0] == 0
    assert "broken tail skipped" in caplog.text


def test_undecodable_records_are_skipped(tmp_path: Path, caplog) -> None:
    good = mixed(2)
    path = tmp_path / "odd.mcap"
    with path.open("wb") as f:
        writer = Writer(f, compression=CompressionType.NONE)
        writer.start()
        schema = writer.register_schema("x", SchemaEncoding.JSONSchema, b"{}")
        packed = writer.register_channel("derl/run1/x", MessageEncoding.MessagePack, schema)
        as_json = writer.register_channel("derl/run1/y", MessageEncoding.JSON, schema)
        raw = {**good[0].model_dump(), "schema_version": 99}
        for channel, data in [
            (packed, encode(good[0])),
            (packed, b"\xc1garbage"),
            (packed, msgpack.packb(raw)),
            (as_json, b"{}"),
            (packed, encode(good[1])),
        ]:
            writer.add_message(channel, log_time=1, data=data, publish_time=1)
        writer.finish()
    with caplog.at_level(logging.WARNING, logger="derl.nodes.journal.segments"):
        assert list(read_segment(path)) == good
    assert "not msgpack" in caplog.text
    assert "schema version 99" in caplog.text
    assert "non-msgpack channel" in caplog.text


def test_a_journal_of_another_schema_version_is_refused_as_a_whole(tmp_path: Path) -> None:
    """A journal written by the derl before this one's schema (version 4: its messages named the
    agent `child`): every message of it would be skipped, and a coordinator would have started
    the run again from nothing in its directory. It is refused in one line instead, by the
    coordinator (exit status 78) and by every reader."""
    old = SCHEMA_VERSION - 1
    (tmp_path / "journal").mkdir()
    path = tmp_path / "journal" / "segment-0001.mcap"
    with path.open("wb") as f:
        writer = Writer(f, compression=CompressionType.NONE)
        writer.start()
        schema = writer.register_schema("Birth", SchemaEncoding.JSONSchema, b"{}")
        channel = writer.register_channel("derl/run1/births", MessageEncoding.MessagePack, schema,
                                          {"schema_version": str(old)})  # fmt: skip
        birth = mixed(13)[-1].model_dump()
        raw = {**birth, "schema_version": old, "child": birth.pop("agent")}
        writer.add_message(channel, log_time=1, data=msgpack.packb(raw), publish_time=1)
        writer.finish()
    said = f"schema version {old}, and this derl reads version {SCHEMA_VERSION}"
    for read in (lambda: list(read_segment(path)), lambda: list(replay(tmp_path))):
        with pytest.raises(DerlError, match=said):
            read()
    with pytest.raises(DerlError) as refused:
        Coordinator("run1", tmp_path, EvolutionRules("run1", tmp_path, load_profile("smoke")))
    assert refused.value.code == REFUSED and "derl that wrote it" in str(refused.value)
    assert segments(tmp_path) == [path]  # no new segment was started beside it


V4_CHILD = {"Tournament", "TrainJob", "TrainProgress", "FitnessReport", "Ack", "Reject", "Birth",
            "ChildFailed", "Quarantine", "Retrained"}  # fmt: skip


def _as_version_4(msg: MessageBase) -> bytes:
    """`msg` as the derl of schema version 4 wrote it: its agent named `child` or `subject`."""
    raw = msgpack.unpackb(encode(msg))
    raw["schema_version"] = 4
    if msg.type in V4_CHILD:
        raw["child"] = raw.pop("agent")
    elif msg.type == "JobFailed":
        raw["subject"] = raw.pop("agent")
    return msgpack.packb(raw)


def test_a_version_4_journal_is_upgraded_in_place(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`derl log upgrade RUN_DIR`: every message of a version-4 journal, in order with its times,
    as this version's (its agent renamed, nothing else), the old segments kept beside it; a
    second upgrade is refused."""
    from derl.nodes.cli.main import main

    sent = mixed(2 * len(MESSAGE_TYPES))
    (tmp_path / "journal").mkdir()
    for n, part in enumerate((sent[:7], sent[7:])):
        path = tmp_path / "journal" / f"segment-{n + 1:04d}.mcap"
        with path.open("wb") as f:
            writer = Writer(f, compression=CompressionType.NONE)
            writer.start()
            schema = writer.register_schema("any", SchemaEncoding.JSONSchema, b"{}")
            channel = writer.register_channel("derl/run1/x", MessageEncoding.MessagePack, schema,
                                              {"schema_version": "4"})  # fmt: skip
            for k, msg in enumerate(part):
                writer.add_message(channel, log_time=100 + k, data=_as_version_4(msg),
                                   publish_time=k)  # fmt: skip
            writer.finish()
    old = {p.name: p.read_bytes() for p in segments(tmp_path)}
    with pytest.raises(DerlError, match="schema version 4"):
        list(replay(tmp_path))
    assert main(["log", "upgrade", str(tmp_path)]) == 0
    said = capsys.readouterr().out
    upgraded = f"{tmp_path}/journal/segment-0002.mcap: {len(sent) - 7} messages"
    assert f"journal.v4/segment-0002.mcap -> {upgraded}" in said
    assert list(replay(tmp_path)) == sent
    times = [(m.log_time, m.publish_time) for p in segments(tmp_path) for m in read_logged(p)]
    assert times == [(100 + k, k) for part in (sent[:7], sent[7:]) for k in range(len(part))]
    kept = tmp_path / "journal.v4"
    assert {p.name: p.read_bytes() for p in kept.iterdir()} == old
    with pytest.raises(SystemExit) as refused:
        main(["log", "upgrade", str(tmp_path)])
    assert refused.value.code == 1 and "journal.v4 exists" in capsys.readouterr().err


def test_a_corrupt_chunk_is_skipped_with_a_warning_and_reading_goes_on(
    tmp_path: Path, caplog
) -> None:
    written = payloads(mixed(20))
    path = tmp_path / "flip.mcap"
    closed_file(path, written)
    data = bytearray(path.read_bytes())
    at = data.find(written[10])
    data[at + len(written[10]) // 2] ^= 0x40
    path.write_bytes(data)
    with caplog.at_level(logging.WARNING, logger="derl.nodes.journal.segments"):
        assert payloads(list(read_segment(path))) == written[:10] + written[11:]
    assert "CRCValidationError" in caplog.text and "whole records follow" in caplog.text


def _crashed_segment(run_dir: Path, written: list[bytes]) -> Path:
    """The one segment of `run_dir` as a crash leaves it: every message flushed, no footer."""
    journal = Journal(run_dir)
    for payload in written:
        journal.write(decode(payload))
    kept = journal.segment.read_bytes()
    journal.close()
    journal.segment.write_bytes(kept)
    return journal.segment


def test_damage_followed_by_whole_records_in_the_last_segment_is_no_torn_tail(
    tmp_path: Path,
) -> None:
    """A crash only cuts the end of the segment being written: a bad record with whole ones after
    it is damage. The replay and a restart refuse it (they once cut the segment there, dropping
    every later record, acknowledged births included); nothing is cut."""
    written = payloads(mixed(60))
    segment = _crashed_segment(tmp_path, written)
    data = bytearray(segment.read_bytes())
    at = data.find(written[30])
    data[at + 3] ^= 0x40
    segment.write_bytes(data)
    with pytest.raises(JournalDamaged, match="whole records follow it from byte") as raised:
        list(replay(tmp_path))
    assert raised.value.end < at < (raised.value.resumes or 0)
    assert "derl log repair" in str(raised.value)
    with pytest.raises(JournalDamaged, match="not the torn tail"):
        Journal(tmp_path)
    assert segment.read_bytes() == data and segments(tmp_path) == [segment]


def test_a_torn_tail_is_cut_at_any_byte_and_a_zeroed_one_too(tmp_path: Path) -> None:
    """What a crash leaves at the end of the last segment (a record cut anywhere, or the file
    grown with zeros the data never reached) is cut back to the last whole record."""
    written = payloads(mixed(12))
    segment = _crashed_segment(tmp_path, written)
    data = segment.read_bytes()
    last = data.find(written[-1])
    for tail in (data[: last + 5], data[: last + 5] + bytes(4000), data[:last] + bytes(100)):
        segment.write_bytes(tail)
        back = payloads(list(replay(tmp_path)))
        assert back == written[: len(back)] and len(back) >= len(written) - 2
        with Journal(tmp_path) as journal:
            assert payloads(list(journal.replay())) == back
        journal.segment.unlink()


CHILD = """
import sys
from derl.messages import TrainProgress
from derl.nodes.journal.segments import Journal

journal = Journal(sys.argv[1])
for i in range(10**9):
    journal.write(TrainProgress(run="run1", agent=f"a{i}", job="j", node="n", env_steps=i,
                                total_steps=10**12, recent_return=None, steps_per_s=1.0))
    print(i + 1, flush=True)
"""


def test_sigkilled_writer_loses_nothing_it_reported(tmp_path: Path, caplog) -> None:
    child = subprocess.Popen(
        [sys.executable, "-c", textwrap.dedent(CHILD), str(tmp_path)],
        stdout=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    reported = 0
    try:
        assert child.stdout is not None
        for line in child.stdout:
            reported = int(line)
            if reported >= 300:
                break
        os.kill(child.pid, signal.SIGKILL)
        child.wait(timeout=10)
        reported = max([reported, *map(int, child.stdout.read().split())])
    finally:
        if child.poll() is None:
            os.killpg(child.pid, signal.SIGKILL)
            child.wait(timeout=10)
    assert child.returncode == -signal.SIGKILL
    back = list(replay(tmp_path))
    assert 300 <= reported <= len(back) <= reported + 1
    assert [m.env_steps for m in back] == list(range(len(back)))  # type: ignore[attr-defined]
    with (
        caplog.at_level(logging.INFO, logger="derl.nodes.journal.segments"),
        Journal(tmp_path) as journal,  # a restart: a new segment, the old one stays readable
    ):
        assert journal.segment.name == "segment-0002.mcap"
        journal.write(mixed(1)[0])
        assert len(list(journal.replay())) == len(back) + 1
    # the restart says once what it found at the killed segment's end: no footer, or a torn tail
    said = [r.getMessage() for r in caplog.records if "segment-0001" in r.getMessage()]
    assert len(said) == 1 and ("has no footer" in said[0] or "torn tail" in said[0]), said


def _by_mcap(path: Path) -> list[tuple[int, int, bytes]]:
    """The messages the `mcap` package's own stream reader reads, up to its first error."""
    read = []
    with path.open("rb") as f:
        try:
            for record in StreamReader(f, validate_crcs=True).records:
                if isinstance(record, Message):
                    read.append((record.channel_id, record.sequence, record.data))
        except Exception:  # a cut or corrupt record: what came before it
            pass
    return read


def test_the_reader_reads_what_the_mcap_package_reads(tmp_path: Path) -> None:
    """`records` is a faster walk of its own: on a journal segment, a compacted one (zstd
    chunks, indexes, summary) and either cut at any byte, it reads the same messages."""
    pytest.importorskip("zstandard")
    written = payloads(mixed(150))
    plain, packed = tmp_path / "plain.mcap", tmp_path / "packed.mcap"
    closed_file(plain, written)
    packed.write_bytes(plain.read_bytes())
    assert compact(packed)
    rng = random.Random(3)
    cut = tmp_path / "cut.mcap"
    for path in (plain, packed):
        data = path.read_bytes()
        for size in [*rng.sample(range(len(data)), 40), len(data)]:
            cut.write_bytes(data[:size])
            mine = [(r.channel_id, r.sequence, r.data) for r in records(cut)
                    if isinstance(r, Message)]  # fmt: skip
            assert mine == _by_mcap(cut), (path.name, size)
        assert len(mine) == len(written)


def test_compaction_keeps_every_message(tmp_path: Path) -> None:
    pytest.importorskip("zstandard")
    written = payloads(mixed(200))
    closed, crashed = tmp_path / "closed.mcap", tmp_path / "crashed.mcap"
    closed_file(closed, written)
    data = closed.read_bytes()
    crashed.write_bytes(data[: data.find(written[150])])
    before = closed.stat().st_size
    assert compact(closed) and compact(crashed)
    assert closed.stat().st_size < before / 2
    assert payloads(list(read_segment(closed))) == written
    assert payloads(list(read_segment(crashed))) == written[:150]
    for path, count in ((closed, 200), (crashed, 150)):
        with path.open("rb") as f:
            summary = make_reader(f).get_summary()
        assert summary is not None and summary.statistics is not None
        assert summary.statistics.message_count == count
        assert {c.compression for c in summary.chunk_indexes} == {"zstd"}
        assert len(summary.channels) == len(MESSAGE_TYPES)


def test_a_journal_that_cannot_be_written_keeps_what_it_could_not_write_until_it_can(
    full_disk: FullDisk,
) -> None:
    """A full disk (a real write fault): the journal raises nothing where it writes, `sync`
    raises its `JournalFault` (naming the file and why), and `recover` fails while the disk is
    full, leaving no new segment behind; once the disk has room it cuts the segment back to
    what was synced and writes the rest into a new one: every message once, in order."""
    written = mixed(60)
    journal = Journal(full_disk.path / "run")
    for msg in written[:20]:
        journal.write(msg, flush=False)
    journal.flush()
    journal.sync()
    full_disk.fill([os.getpid()])
    try:
        for msg in written[20:40]:
            journal.write(msg, flush=False)
        journal.flush()
        with pytest.raises(JournalFault, match=r"cannot write .*segment-0001\.mcap: ") as fault:
            journal.sync()
        assert fault.value.errno in (errno.ENOSPC, errno.EFBIG)
        for msg in written[40:50]:  # while it cannot write: kept, nothing tried
            journal.write(msg, flush=False)
        journal.flush()
        assert journal.recover() is None
        assert segments(full_disk.path / "run") == [journal.segment]
    finally:
        full_disk.free()
    assert journal.recover() == 30
    assert journal.segment.name == "segment-0002.mcap"
    for msg in written[50:]:
        journal.write(msg)
    journal.sync()
    journal.close()
    assert payloads(list(replay(full_disk.path / "run"))) == payloads(written)
