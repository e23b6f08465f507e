"""The coordinator's disk side: checkpoint files written in batches by a writer process (one
syncfs, or one fsync per file where there is none; a repeat's link to a file of the same batch;
one bad file fails alone; a writer process that dies fails its batch, the next starts another)
and the outbox (replies released once the journal is synced, an Ack only once its checkpoint is
on disk and never if the write failed, jobs and births not held behind it; a failed sync holds
every reply until the journal is written again, a fault of its own stops the coordinator instead
of stalling it), and what could not be written said once a minute."""

from __future__ import annotations

import errno
import logging
import subprocess
import sys
import threading
from concurrent.futures import Future
from pathlib import Path

import msgpack
import pytest

from derl.messages import Ack, RunStatus
from derl.nodes.coordinator.disk_faults import DiskFaults
from derl.nodes.coordinator.outbox import Outbox
from derl.nodes.journal.segments import Journal, read_segment
from derl.nodes.runtime import checkpoint_writer
from derl.nodes.runtime.checkpoint_writer import write_batch
from derl.nodes.runtime.checkpoints import CheckpointFiles
from derl.nodes.testing.waiting import ManualClock, wait_until


def test_a_batch_of_checkpoints_is_written_whole_and_links_share_its_files(
    tmp_path: Path,
) -> None:
    files = CheckpointFiles(tmp_path)
    saved = {f"a{k}": files.save(f"a{k}", f"weights-{k}".encode()) for k in range(20)}
    linked = files.link("r0", "a19")  # a file that may be in the same batch
    bad = files.save("missing/a", b"x")  # its folder does not exist: fails alone
    for future in [*saved.values(), linked]:
        assert future.result(timeout=10) is None
    error = bad.exception(timeout=10)
    assert isinstance(error, OSError) and error.errno == errno.ENOENT
    assert "missing/a.pt.tmp" in str(error)
    writer = files._process.process
    files.close()
    assert writer is not None and writer.poll() == 0  # the writer process ended with it
    for k in range(20):
        assert files.path(f"a{k}").read_bytes() == f"weights-{k}".encode()
    assert files.path("r0").stat().st_ino == files.path("a19").stat().st_ino
    assert not list(files.folder.glob("*.tmp"))


def test_a_link_whose_source_file_is_missing_waits_for_it(tmp_path: Path) -> None:
    """After a crash, a repeat's link may come before its source's file, which comes back with
    the source's re-sent report: the link waits for it (it failed, and nothing made it again:
    found by bench/crash.py), and fails only if the file never comes."""
    files = CheckpointFiles(tmp_path)
    waits = files.link("r0", "a0")
    never = files.link("r1", "a9")
    assert files.save("b0", b"w").result(timeout=10) is None  # written after the links' turn
    assert not waits.done() and not never.done()
    assert files.save("a0", b"w0").result(timeout=10) is None
    assert waits.result(timeout=10) is None
    assert files.path("r0").read_bytes() == b"w0"
    files.close()
    assert isinstance(never.exception(timeout=10), FileNotFoundError)
    assert not files.path("r1").exists()


def test_without_syncfs_each_file_is_fsynced(tmp_path: Path) -> None:
    """Where there is no syncfs (not Linux), the same batch with one fsync per file."""
    batch = {"a0": b"w0", "r0": "a0", "missing/a": b"x", "big": bytes(3 << 20)}
    failures = write_batch(tmp_path, batch, syncfs=None)
    assert isinstance(failures.pop("missing/a"), OSError)
    assert failures == {"a0": None, "r0": None, "big": None}
    assert (tmp_path / "big.pt").stat().st_size == 3 << 20
    assert (tmp_path / "r0.pt").stat().st_ino == (tmp_path / "a0.pt").stat().st_ino


def test_a_writer_process_that_dies_fails_its_batch_and_the_next_starts_another(
    tmp_path: Path,
) -> None:
    files = CheckpointFiles(tmp_path)
    assert files.save("a0", b"w0").result(timeout=10) is None
    first = files._process.process
    assert first is not None
    first.kill()
    first.wait()
    lost = files.save("a1", b"w1").exception(timeout=10)
    assert isinstance(lost, OSError) and "checkpoint writer process ended" in str(lost)
    assert files.save("a1", b"w1").result(timeout=10) is None  # the trainer's re-sent report
    assert files._process.process not in (None, first)
    files.close()
    assert files.path("a1").read_bytes() == b"w1"


def _status(run: str, born: int) -> RunStatus:
    return RunStatus(run=run, born=born, target=10, in_flight=0, workers_alive=0)


def test_the_outbox_releases_after_the_sync_and_an_ack_after_its_checkpoint(
    tmp_path: Path,
) -> None:
    journal = Journal(tmp_path)
    synced: list[int] = []

    def sync() -> None:
        journal.sync()
        synced.append(len(list(read_segment(journal.segment))))

    outbox = Outbox(sync)
    ack = Ack(run="r", of="FitnessReport", job="j1", agent="c1", node="n1")
    written, lost = Future(), Future()
    for future in (written, lost):
        future.set_running_or_notify_cancel()
    first, later = _status("r", 1), _status("r", 2)
    journal.write(first, flush=False)
    journal.flush()
    outbox.send([(ack, b"ack", written), (first, b"first", None)])
    outbox.send([(ack, b"lost", lost), (later, b"later", None)])
    # the two statuses are released; the Acks wait for their files
    wait_until(lambda: outbox._pending <= 2, 10, "the statuses released")
    assert synced and synced[0] >= 1, "released before the journal file was synced"
    assert [data for _, data in outbox.take()] == [b"first", b"later"]

    written.set_result(None)
    full = OSError(errno.ENOSPC, "No space left on device")
    lost.set_exception(full)
    outbox.drain()
    assert [data for _, data in outbox.take()] == [b"ack"]  # the lost one is never sent
    outbox.close()
    journal.close()


def test_an_outbox_whose_sync_fails_holds_every_reply_until_it_is_resumed() -> None:
    """A journal that cannot be synced (a full disk) holds what is sent, in order, without
    stopping the coordinator; `drain` does not wait for it; `resume` (the journal written
    again) releases it all, and later groups are synced again."""
    fails = [True]

    def sync() -> None:
        if fails[0]:
            raise OSError(errno.ENOSPC, "No space left on device")

    outbox = Outbox(sync)
    outbox.send([(_status("r", 1), b"first", None)])
    outbox.send([(_status("r", 2), b"second", None)])
    wait_until(lambda: outbox.fault, 10, "the sync's fault")
    assert isinstance(outbox.fault, OSError) and outbox.failure is None
    outbox.send([(_status("r", 3), b"third", None)])  # held too: no sync is tried
    outbox.drain()
    wait_until(lambda: len(outbox._held) == 3, 10, "the third reply held")
    assert outbox.take() == []
    fails[0] = False
    outbox.resume()
    outbox.send([(_status("r", 4), b"fourth", None)])
    outbox.drain()
    assert [data for _, data in outbox.take()] == [b"first", b"second", b"third", b"fourth"]
    assert outbox.fault is None
    outbox.close()


def test_an_outbox_with_a_fault_of_its_own_stops_the_coordinator_instead_of_stalling_it() -> None:
    """Nothing is released once the outbox thread meets a fault of its own: `send` raises it
    from then on (the coordinator's loop stops on it and its supervisor restarts it from the
    journal) and `drain` returns; a thread that just died would leave the loop running with
    every worker waiting for ever."""
    fault = RuntimeError("a bug")

    def sync() -> None:
        raise fault

    outbox = Outbox(sync)
    status = _status("r", 1)
    outbox.send([(status, b"first", None)])
    wait_until(lambda: outbox.failure, 10, "the outbox's failure")
    with pytest.raises(RuntimeError):
        outbox.send([(status, b"second", None)])
    drained = threading.Thread(target=outbox.drain, daemon=True)
    drained.start()
    drained.join(5)
    assert not drained.is_alive(), "drain waits for ever"
    assert outbox.take() == []
    outbox.close()


def test_what_cannot_be_written_is_said_at_once_then_once_a_minute(
    caplog: pytest.LogCaptureFixture,
) -> None:
    clock = ManualClock()
    faults = DiskFaults(clock=clock)
    full = OSError(errno.ENOSPC, "No space left on device")
    with caplog.at_level(logging.WARNING, logger="derl.coordinator"):
        for second in range(130):  # a write tried every second for 130 s
            clock.now = float(second)
            faults.failed(Path("/r/journal/segment-0001.mcap"), full, "it waits")
        faults.works("the journal goes on")
        faults.works("again: nothing to say")
    assert [r.getMessage() for r in caplog.records] == [
        "cannot write /r/journal/segment-0001.mcap (No space left on device): it waits",
        "still cannot write, for 60 s: /r/journal/segment-0001.mcap (No space left on device): "
        "it waits (60 writes failed in the last 60 s)",
        "still cannot write, for 120 s: /r/journal/segment-0001.mcap (No space left on device): "
        "it waits (60 writes failed in the last 60 s)",
        "writing works again, after 129 s: the journal goes on",
    ]


def test_the_checkpoint_writer_ends_quietly_when_its_coordinator_is_gone(tmp_path: Path) -> None:
    """A writer whose coordinator died (nobody reads its answers) ends without a traceback (it
    printed a BrokenPipeError's)."""
    writer = subprocess.Popen(
        [sys.executable, "-I", checkpoint_writer.__file__, str(tmp_path)],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
    )  # fmt: skip
    writer.stdout.close()  # the coordinator is gone
    writer.stdin.write(msgpack.packb({"c00001": b"weights"}, use_bin_type=True))
    writer.stdin.close()
    assert writer.wait(timeout=30) == 0
    assert writer.stderr.read() == b""
    assert (tmp_path / "c00001.pt").read_bytes() == b"weights"  # written all the same


def test_a_signal_to_the_coordinators_process_group_never_ends_its_checkpoint_writer(
    tmp_path: Path,
) -> None:
    """A launcher stops a coordinator with SIGTERM to its process group (a terminal's Ctrl-C
    reaches the group too): the writer, even while it starts, writes on (it died there with
    exit code -15, the file of a birth already journaled lost)."""
    script = (
        "import os, signal, sys, time\n"
        "from derl.nodes.runtime.checkpoints import CheckpointFiles\n"
        "signal.signal(signal.SIGTERM, lambda *_: None)  # the coordinator stops in order\n"
        "files = CheckpointFiles(sys.argv[1])\n"
        "saved = files.save('c00001', b'weights')\n"
        "while files._process.process is None:  # until the writer is spawned\n"
        "    time.sleep(0.0001)\n"
        "os.killpg(0, signal.SIGTERM)  # while it starts\n"
        "print(saved.exception())\n"
        "files.close()\n"
    )
    done = subprocess.run([sys.executable, "-c", script, str(tmp_path)], capture_output=True,
                          text=True, timeout=60, start_new_session=True)  # fmt: skip
    assert (done.returncode, done.stdout) == (0, "None\n"), done.stderr
    assert (tmp_path / "checkpoints" / "c00001.pt").read_bytes() == b"weights"
