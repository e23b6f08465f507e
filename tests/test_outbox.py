"""The coordinator's disk side: checkpoint files written in batches (one syncfs, or one fsync per
file where there is none; a repeat's link to a file of the same batch; one bad file fails alone)
and the outbox (replies released once the journal is synced, an Ack only once its checkpoint is
on disk and never if the write failed, jobs and births not held behind it)."""

from __future__ import annotations

from concurrent.futures import Future
from pathlib import Path

import pytest

from messages import Ack, RunStatus
from nodes.coordinator.outbox import Outbox
from nodes.journal.segments import Journal, read_segment
from nodes.runtime import checkpoints
from nodes.runtime.checkpoints import CheckpointFiles


@pytest.mark.parametrize("syncfs", [True, False], ids=["syncfs", "fsync-per-file"])
def test_a_batch_of_checkpoints_is_written_whole_and_links_share_its_files(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, syncfs: bool
) -> None:
    if not syncfs:
        monkeypatch.setattr(checkpoints, "_syncfs", None)
    elif checkpoints._syncfs is None:
        pytest.skip("no syncfs on this platform")
    files = CheckpointFiles(tmp_path)
    saved = {f"a{k}": files.save(f"a{k}", f"weights-{k}".encode()) for k in range(20)}
    linked = files.link("r0", "a19")  # a file that may be in the same batch
    bad = files.save("missing/a", b"x")  # its folder does not exist: fails alone
    for future in [*saved.values(), linked]:
        assert future.result(timeout=10) is None
    assert isinstance(bad.exception(timeout=10), OSError)
    files.close()
    for k in range(20):
        assert files.path(f"a{k}").read_bytes() == f"weights-{k}".encode()
    assert files.path("r0").stat().st_ino == files.path("a19").stat().st_ino
    assert not list(files.folder.glob("*.tmp"))


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
    ack = Ack(run="r", of="FitnessReport", job="j1", child="c1", node="n1")
    written, lost = Future(), Future()
    for future in (written, lost):
        future.set_running_or_notify_cancel()
    first, later = _status("r", 1), _status("r", 2)
    journal.write(first, flush=False)
    journal.flush()
    outbox.send([(ack, b"ack", written), (first, b"first", None)])
    outbox.send([(ack, b"lost", lost), (later, b"later", None)])
    while outbox._pending > 2:  # the two statuses are released; the Acks wait for their files
        outbox.released.wait(1)
    assert synced and synced[0] >= 1, "released before the journal file was synced"
    assert [data for _, data in outbox.take()] == [b"first", b"later"]

    written.set_result(None)
    lost.set_exception(OSError("disk full"))
    outbox.drain()
    assert [data for _, data in outbox.take()] == [b"ack"]  # the lost one is never sent
    outbox.close()
    journal.close()
