"""The offline log tools on real MCAP files: JSON export for Foxglove, `log info` on clean,
truncated, corrupt and foreign files, repair of a truncated file, run directories, and the
`derl export` / `derl log` command lines."""

from __future__ import annotations

import base64
import json
import math
import subprocess
import sys
from pathlib import Path

import pytest
from mcap.reader import make_reader
from mcap.well_known import MessageEncoding, SchemaEncoding
from mcap.writer import Writer

from messages import FitnessReport, MessageBase, encode
from messages.examples import examples
from nodes.journal.segments import Journal, JournalWriter
from nodes.tools.logs import LogError, export_json, info, read_log, repair

STEPS = 5


def _messages(run: str = "r1") -> list[MessageBase]:
    sent = [m for i in range(STEPS) for m in examples(run, i)]
    report = next(m for m in sent if isinstance(m, FitnessReport))
    return [*sent, report.model_copy(update={"child": "a99", "energy": math.nan})]


@pytest.fixture
def log(tmp_path: Path) -> Path:
    path = tmp_path / "run.mcap"
    with JournalWriter(path) as writer:
        for message in _messages():
            writer.write(message)
    return path


def _cut(log: Path, fraction: float) -> Path:
    """A copy of `log` cut at `fraction` of its data: what a killed writer leaves."""
    data = log.read_bytes()
    cut = log.with_name("cut.mcap")
    cut.write_bytes(data[: int(len(data) * fraction)])
    return cut


def _same(a: list[MessageBase], b: list[MessageBase]) -> bool:
    """Equal messages, NaN fields included (as their wire bytes)."""
    return [encode(m) for m in a] == [encode(m) for m in b]


def test_export_writes_json_and_jsonschema_that_parse(log: Path, tmp_path: Path) -> None:
    out = tmp_path / "run.json.mcap"
    assert export_json(log, out) == len(_messages())
    with out.open("rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics.message_count == len(_messages())
        assert {c.compression for c in summary.chunk_indexes} == {"zstd"}
        assert {c.message_encoding for c in summary.channels.values()} == {"json"}
        assert {s.encoding for s in summary.schemas.values()} == {"jsonschema"}
        for schema in summary.schemas.values():
            assert json.loads(schema.data)["properties"]["type"]["const"] == schema.name
        decoded = [
            (schema.name, json.loads(message.data))
            for schema, _, message in reader.iter_messages(log_time_order=False)
        ]
    report_schema = next(s for s in summary.schemas.values() if s.name == "FitnessReport")
    checkpoint = json.loads(report_schema.data)["properties"]["checkpoint"]
    assert checkpoint["contentEncoding"] == "base64" and "format" not in checkpoint
    reports = [body for name, body in decoded if name == "FitnessReport"]
    originals = [m for m in _messages() if isinstance(m, FitnessReport)]
    assert [base64.b64decode(r["checkpoint"]) for r in reports] == [m.checkpoint for m in originals]
    assert reports[-1]["energy"] is None  # NaN is not JSON
    assert [body["type"] for _, body in decoded] == [m.type for m in _messages()]


def test_export_refuses_a_foreign_file_and_an_existing_output(log: Path, tmp_path: Path) -> None:
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not an mcap file at all")
    with pytest.raises(LogError, match="not an MCAP file"):
        export_json(junk, tmp_path / "out.mcap")
    assert not (tmp_path / "out.mcap").exists()
    with pytest.raises(FileExistsError):
        export_json(log, junk)


def test_info_on_a_clean_log(log: Path) -> None:
    (file,) = info(log)
    assert (file.integrity, file.indexed, file.undecodable) == ("clean", True, 0)
    assert file.messages == len(_messages())
    counts = {(c.topic, c.schema): c.count for c in file.channels}
    assert counts[("derl/r1/fitness", "FitnessReport")] == STEPS + 1
    assert counts[("derl/r1/job", "TrainJob")] == counts[("derl/r1/job", "EvalJob")] == STEPS
    assert {c.encoding for c in file.channels} == {"msgpack"}
    assert 0 < file.span_s < 10


def test_a_truncated_log_gives_its_prefix_and_repairs(log: Path, tmp_path: Path) -> None:
    cut = _cut(log, 0.4)
    (file,) = info(cut)
    assert file.integrity == "truncated" and not file.indexed
    recovered = [entry.message for entry in read_log(cut)]
    assert 0 < len(recovered) == file.messages < len(_messages())
    assert _same(recovered, _messages()[: len(recovered)])
    fixed = repair(cut, tmp_path / "fixed.mcap")
    assert (fixed.integrity, fixed.indexed, fixed.compression) == ("clean", True, ["zstd"])
    assert _same([e.message for e in read_log(tmp_path / "fixed.mcap")], recovered)
    with pytest.raises(LogError, match="exists"):
        repair(cut, tmp_path / "fixed.mcap")


def test_a_corrupt_byte_is_reported_with_what_is_readable(log: Path) -> None:
    data = bytearray(log.read_bytes())
    data[len(data) // 3] ^= 0xFF
    log.write_bytes(bytes(data))
    (file,) = info(log)
    assert file.integrity == "corrupt"
    assert 0 < file.messages < len(_messages())
    assert f"of {len(_messages())} messages readable" in file.detail


def test_undecodable_messages_are_counted_and_skipped(tmp_path: Path) -> None:
    path = tmp_path / "mixed.mcap"
    good = _messages()[0]
    with path.open("wb") as f:
        writer = Writer(f)
        writer.start()
        schema = writer.register_schema("WorkerReady", SchemaEncoding.JSONSchema, b"{}")
        channel = writer.register_channel("derl/r1/ready", MessageEncoding.MessagePack, schema)
        for data in (b"\xc1garbage", good.model_dump_json().encode()):
            writer.add_message(channel, log_time=1, data=data, publish_time=1)
        writer.add_message(channel, log_time=2, data=encode(good), publish_time=2)
        writer.finish()
    (file,) = info(path)
    assert (file.messages, file.undecodable, file.integrity) == (3, 2, "clean")
    assert [entry.message for entry in read_log(path)] == [good]


def test_a_run_directory_is_read_segment_by_segment(tmp_path: Path) -> None:
    first, second = _messages()[:10], _messages()[10:20]
    for part in (first, second):
        with Journal(tmp_path / "run") as journal:
            for message in part:
                journal.write(message)
    assert [entry.message for entry in read_log(tmp_path / "run")] == first + second
    assert [f.messages for f in info(tmp_path / "run")] == [10, 10]
    with pytest.raises(LogError, match="no journal"):
        info(tmp_path)


def _derl(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "nodes.cli", *args], capture_output=True, text=True, timeout=60
    )


def test_command_lines(log: Path, tmp_path: Path) -> None:
    done = _derl("log", "info", str(_cut(log, 0.4)))
    assert done.returncode == 3 and "integrity:   truncated" in done.stdout
    assert "derl log repair" in done.stdout
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"\x00" * 100)
    done = _derl("log", "info", str(junk))
    assert done.returncode == 1 and "not an MCAP file" in done.stderr
    assert "Traceback" not in done.stderr
    done = _derl("export", str(log), "--json", str(tmp_path / "out.mcap"))
    assert done.returncode == 0 and f"exported {len(_messages())} messages" in done.stdout
    done = _derl("log", "info", "--json", str(tmp_path / "out.mcap"))
    assert json.loads(done.stdout)[0]["integrity"] == "clean"
