"""Crash consistency, checked on a small real run recorded under strace (`derl.nodes.testing`'s
`crash`, `disk` and `crash_check`; tests/test_crash_check.py checks the checker itself): the
run directory rebuilt as a process kill or a power cut at each point of the run's writes would
leave it (torn journal writes included), and the coordinator started on it. Every state is
checked for what a start must find; a sample of them, and the state where the run's last
birth is journaled but its checkpoint is not in place, are run to the end in this process, and one
with a real `derl coordinator` and trainers over Zenoh. `python bench/crash.py` runs every state to
the end."""

from __future__ import annotations

import random
import shutil
import subprocess

import pytest

from derl.messages import Birth
from derl.nodes.testing import crash
from derl.nodes.testing.crash_check import check_cut, holds_at_start
from derl.nodes.testing.disk import Cut

pytestmark = [pytest.mark.slow, pytest.mark.xdist_group(name="crash")]


def _strace_works() -> bool:
    if shutil.which("strace") is None:
        return False
    done = subprocess.run(["strace", "-f", "-qq", "-o", "/dev/null", "true"], capture_output=True)
    return done.returncode == 0


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> crash.Recorded:
    if not _strace_works():
        pytest.skip("recording needs a working strace (apt-get install strace; ptrace allowed)")
    return crash.record_and_cut(tmp_path_factory.mktemp("crash"))


def test_every_crash_state_holds_what_the_trainers_were_told(recorded: crash.Recorded) -> None:
    """A start accepts every state (a torn tail is cut, nothing is refused), and its journal
    holds every job a trainer had received and every birth it had acknowledged, with the
    checkpoint file that trainer sent. (Before the journal synced its folder when it created a
    segment, a power cut could lose the whole segment, and with it the jobs it had published.)"""
    kinds = recorded.tried
    assert min(kinds[k] for k in ("kill", "power", "kill-torn", "power-torn", "power-zeros")) > 50
    assert recorded.refused == []
    broken = {(c.index, c.kind, c.torn_at): holds_at_start(recorded, c)
              for c in recorded.distinct}  # fmt: skip
    assert {cut: problems for cut, problems in broken.items() if problems} == {}


def test_sampled_crash_states_run_to_the_end(recorded: crash.Recorded) -> None:
    """Started on the state, the coordinator runs the run to its end with the trainers as they
    were: no acknowledged birth lost, none born twice, every body born with its checkpoint, the
    best ones' folders whole. The sample: the state where the last birth is journaled and its
    checkpoint is not in place (`crash.last_checkpoint_late`), and 10 others drawn at random."""
    end = crash.last_checkpoint_late(recorded)
    births = {m.agent for m in crash.journaled(recorded, end) if isinstance(m, Birth)}
    assert len(births) == crash.config().total
    files = {name.removeprefix("checkpoints/").removesuffix(".pt") for name in end.state}
    assert not births <= files
    others = random.Random(1).sample(recorded.distinct, 10)
    failures = [check_cut(recorded, cut) for cut in [end, *others]]
    assert [f for f in failures if f] == []


def test_a_real_coordinator_resumes_a_crash_at_the_end_and_mid_run(
    recorded: crash.Recorded,
) -> None:
    """A real `derl coordinator` and the trainers over real Zenoh run the run to its end from a
    kill just after the last birth was journaled, before its checkpoint was in place (the results
    were written at the first 'done' and missed the checkpoint its trainer sent again: the best
    body had none), and from a power cut (or, where none left another state, a kill) after some
    births were acknowledged while a trainer waited for its Ack."""
    end = crash.last_checkpoint_late(recorded)
    total = crash.config().total

    # A power cut halfway, a trainer waiting for its Ack if there is one. Where the disk was in
    # sync, a power cut leaves what a kill leaves, and `distinct` keeps that state as a kill:
    # whether any mid-run power state differs depends on the recorded run's timing, so a kill
    # state stands in when none does.
    def rank(cut: Cut) -> tuple[bool, bool, float]:
        waiting = any(not answered for _, _, answered in cut.knowledge.holding)
        return cut.kind == "power", waiting, -abs(len(cut.knowledge.acked) - total / 2)

    mid = max((c for c in recorded.distinct if c.kind in ("power", "kill") and
               0 < len(c.knowledge.acked) < total), key=rank)  # fmt: skip
    assert check_cut(recorded, end, real=True) is None
    assert check_cut(recorded, mid, real=True) is None
