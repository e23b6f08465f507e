"""The offline log tools on real MCAP files: JSON export for Foxglove, `log info` on clean,
truncated, corrupt and foreign files, repair of a truncated file, run directories, and the
`derl export` / `derl log` command lines."""

from __future__ import annotations

import base64
import json
import math
import re
import subprocess
import sys
from pathlib import Path

import pytest
from mcap.reader import make_reader
from mcap.well_known import MessageEncoding, SchemaEncoding
from mcap.writer import Writer
from nodes_fixtures import Processes, derl_argv

from derl.messages import Birth, FitnessReport, MessageBase, encode, kind_of
from derl.messages.examples import examples
from derl.nodes.errors import REFUSED
from derl.nodes.journal.history import load_history
from derl.nodes.journal.segments import Journal, JournalWriter, segments
from derl.nodes.testing.waiting import wait_until
from derl.nodes.tools.logs import LogError, export_json, info, read_log, repair

STEPS = 5


def _messages(run: str = "r1") -> list[MessageBase]:
    sent = [m for i in range(STEPS) for m in examples(run, i)]
    report = next(m for m in sent if isinstance(m, FitnessReport))
    return [*sent, report.model_copy(update={"agent": "a99", "energy": math.nan})]


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


def test_a_truncated_log_gives_its_prefix_and_repairs(
    log: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    cut = _cut(log, 0.4)
    (file,) = info(cut)
    assert file.integrity == "truncated" and not file.indexed
    recovered = [entry.message for entry in read_log(cut)]
    assert 0 < len(recovered) == file.messages < len(_messages())
    assert _same(recovered, _messages()[: len(recovered)])
    caplog.clear()
    fixed = repair(cut, tmp_path / "fixed.mcap")
    assert (fixed.integrity, fixed.indexed, fixed.compression) == ("clean", True, ["zstd"])
    damaged = [r.getMessage() for r in caplog.records if "broken tail" in r.getMessage()]
    assert damaged and all(m.startswith(f"{cut}:") for m in damaged)  # not the new file
    assert _same([e.message for e in read_log(tmp_path / "fixed.mcap")], recovered)
    with pytest.raises(LogError, match="exists"):
        repair(cut, tmp_path / "fixed.mcap")


def test_a_corrupt_byte_is_reported_with_what_is_readable(log: Path) -> None:
    """A byte flipped in a chunk a third into the file (in a message's record: a byte between
    chunks, e.g. in an index a reader does not need, may well not matter)."""
    data = bytearray(log.read_bytes())
    data[data.index(b"stand_height", len(data) // 3) + 3] ^= 0xFF
    log.write_bytes(bytes(data))
    (file,) = info(log)
    assert file.integrity == "corrupt"
    assert 0 < file.messages < len(_messages())
    assert f"{file.messages} of {len(_messages())} readable in all" in file.detail


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


def _ended_by_a_crash(run_dir: Path, messages: list[MessageBase]) -> Path:
    """A segment of `run_dir` as a coordinator SIGKILLed between messages leaves it: every
    record whole, no footer."""
    journal = Journal(run_dir)
    for message in messages:
        journal.write(message)
    kept = journal.segment.read_bytes()
    journal.close()
    journal.segment.write_bytes(kept)
    return journal.segment


def test_a_segment_its_run_went_on_after_is_recovered_not_a_failure(tmp_path: Path) -> None:
    run = tmp_path / "run"
    first, second = _messages()[:10], _messages()[10:20]
    crashed = _ended_by_a_crash(run, first)
    (alone,) = info(run)  # not resumed yet: the run's end is open
    assert alone.integrity == "truncated" and "10 messages recovered" in alone.detail
    with Journal(run) as journal:  # the restarted coordinator's segment
        for message in second:
            journal.write(message)
    assert [(f.integrity, f.messages) for f in info(run)] == [("recovered", 10), ("clean", 10)]
    done = _derl("log", "info", str(run))
    assert done.returncode == 0 and "integrity:   recovered: no footer" in done.stdout
    assert "repair with" not in done.stdout and "1 clean, 1 recovered" in done.stdout
    # damage that is not at the run's end is no crash's doing: corrupt, and a failure
    data = bytearray(crashed.read_bytes())
    data[data.find(encode(first[5])) + 5] ^= 0x40
    crashed.write_bytes(data)
    damaged = info(run)[0]
    assert damaged.integrity == "corrupt" and "will not resume from it" in damaged.detail
    assert "5 messages before the damage, 9 readable in all" in damaged.detail
    done = _derl("log", "info", str(run))
    assert done.returncode == 3 and f"repair with: derl log repair {crashed}" in done.stdout


def test_a_damaged_segment_stops_the_coordinator_and_its_advice_resumes_the_run(
    tmp_path: Path, procs: Processes
) -> None:
    """The coordinator refuses a segment damaged before the run's end, names the command that
    repairs it, and resumes once the repaired file is in the damaged one's place."""
    run = tmp_path / "run"
    messages = _messages()
    with Journal(run) as journal:
        for message in messages[:10]:
            journal.write(message)
    with Journal(run) as journal:
        for message in messages[10:20]:
            journal.write(message)
    first = segments(run)[0]
    data = bytearray(first.read_bytes())
    data[data.find(encode(messages[5])) + 5] ^= 0x40
    first.write_bytes(data)
    coordinator = ["coordinator", "--run", "r1", "--run-dir", str(run), "--listen",
                   "tcp/127.0.0.1:0"]  # fmt: skip
    done = _derl(*coordinator)
    said = done.stderr.strip().splitlines()[-1]
    assert done.returncode == REFUSED and f"{first} is damaged" in said, done.stderr
    advice = re.search(r"`derl (log repair \S+ \S+)`", said)
    assert advice is not None, said
    command = advice[1].split()
    repaired = tmp_path / command[-1]
    assert _derl(*command[:-1], str(repaired)).returncode == 0
    first.replace(tmp_path / "damaged.mcap")  # as the advice says
    repaired.replace(first)
    procs.start("coordinator", derl_argv(*coordinator))
    wait_until(lambda: "journaled messages replayed" in procs.log("coordinator"), 60, "a resume")
    assert "Traceback" not in procs.log("coordinator")
    assert "no tournament decided it (lost with a damaged segment?): skipped" in procs.log(
        "coordinator"
    )


def _derl(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "derl.nodes.cli", *args], capture_output=True, text=True, timeout=60
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


def test_damage_in_the_last_segment_is_damage_for_every_tool(tmp_path: Path) -> None:
    """A bad record with whole records after it, in the segment a crash could have cut, is
    damage, not a torn tail (the coordinator once cut there, dropping every later record, and
    `derl replay` called it a broken tail, replayed the prefix and exited 0): `log info` calls it
    corrupt, the coordinator refuses to start and `replay` refuses (exit 1) unless told to skip the
    damage, each naming `derl log repair`; every reader and the repair keep the records after the
    damage, even those whose channel was defined in the damaged chunk."""
    run = tmp_path / "run"
    messages = _messages()
    crashed = _ended_by_a_crash(run, messages)
    data = bytearray(crashed.read_bytes())
    data[data.find(encode(messages[0])) + 5] ^= 0x40  # the chunk that defines its channel
    crashed.write_bytes(data)
    kept = [entry for entry in read_log(run)]
    assert _same([entry.message for entry in kept], messages[1:])
    births = [m.agent for m in messages[1:] if isinstance(m, Birth)]
    assert [b.agent for b in load_history(run).births] == births  # derl report's reading
    assert [entry.topic for entry in kept] == [f"derl/r1/{kind_of(m)}" for m in messages[1:]]
    done = _derl("log", "info", str(run))
    assert done.returncode == 3 and "integrity:   corrupt: damaged at byte" in done.stdout
    assert "whole records follow" in done.stdout and "will not resume from it" in done.stdout
    done = _derl("coordinator", "--run", "r1", "--run-dir", str(run), "--listen",
                 "tcp/127.0.0.1:0")  # fmt: skip
    said = done.stderr.strip().splitlines()[-1]
    assert done.returncode == REFUSED and "not the torn tail" in said and "derl log repair" in said
    assert crashed.read_bytes() == data  # nothing cut
    replay = ["replay", str(run), "--rate", "0", "--listen", "tcp/127.0.0.1:0"]
    done = _derl(*replay)
    assert done.returncode == 1 and "Traceback" not in done.stderr
    assert done.stderr.count("\n") == 1 and f"derl log repair {crashed} OUT.mcap" in done.stderr
    done = _derl(*replay, "--skip-damaged")
    assert done.returncode == 0 and f"replayed {len(messages) - 1} messages" in done.stdout
    fixed = repair(crashed, tmp_path / "fixed.mcap")
    assert fixed.integrity == "clean" and fixed.messages == len(messages) - 1
    assert _same([entry.message for entry in read_log(tmp_path / "fixed.mcap")], messages[1:])
