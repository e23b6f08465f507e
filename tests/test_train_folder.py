"""`derl train`'s folder (`derl.agent_folder`, `derl.training`): a finished training is not
overwritten, a folder stopped before its first save goes on from the beginning, a finished
training is extended to the same bits every time (its learning rate decaying to 0 at the new
end), TensorBoard goes on where the first start wrote, result.json is strict JSON, a second
Ctrl-C never cuts a save, and a Ctrl-C before the training began leaves nothing and no
traceback; what cannot be is one line and exit status 2 and leaves nothing. Trainings of a few
1,024-step iterations, in this process."""

from __future__ import annotations

import csv
import hashlib
import json
import math
import os
import shutil
import signal
import subprocess
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest
from nodes_fixtures import derl_argv
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from derl.agent_folder import AgentFolder
from derl.nodes.cli.main import main
from derl.training import Stop
from derl.unimal import Genome

BATCH = 8 * 128  # --envs 8: one iteration


@pytest.fixture
def handlers() -> Iterator[None]:
    """`derl train` run here installs its signal handlers: put pytest's back."""
    before = {number: signal.getsignal(number) for number in (signal.SIGINT, signal.SIGTERM)}
    yield
    for number, handler in before.items():
        signal.signal(number, handler)


def _train(*arguments: str) -> int:
    try:
        return main(["train", *arguments])
    except SystemExit as end:
        return int(end.code or 0)


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _strict(path: Path) -> dict:
    def refuse(constant: str) -> None:
        raise ValueError(f"{constant} in {path.name}")

    return json.loads(path.read_text(), parse_constant=refuse)


def test_a_finished_training_is_protected_extended_and_strict(
    quadruped: Genome, tmp_path: Path, handlers: None, capsys: pytest.CaptureFixture[str]
) -> None:
    genome, out, board = tmp_path / "body.json", tmp_path / "body-ft", tmp_path / "tb"
    genome.write_text(quadruped.model_dump_json())
    new = ("--genome", str(genome), "--out", str(out), "--envs", "8")
    settings = tmp_path / "ppo.yaml"
    settings.write_text("ppo:\n  lr: 1.0e-4\n  epochs: 3\n")
    assert _train(*new, "--steps", str(2 * BATCH), "--tensorboard", str(board),
                  "--settings", str(settings), "--set", "ppo.epochs=2") == 0  # fmt: skip
    folder = AgentFolder(out)
    ppo = folder.settings().ppo
    assert (ppo.lr, ppo.epochs) == (1e-4, 2) and folder.settings().tensorboard == board.resolve()
    finished = _sha(out / "checkpoint.pt")

    # a finished training is not overwritten: one line, exit status 2
    capsys.readouterr()
    assert _train(*new, "--steps", str(2 * BATCH)) == 2
    said = capsys.readouterr().err
    assert "holds a finished training: extend it with `derl train --resume" in said
    assert _sha(out / "checkpoint.pt") == finished
    # one line and exit status 2, nothing left behind, for what cannot be
    cannot = {("--tensorboard", "/proc/tb"): "--tensorboard /proc/tb: cannot make /proc/tb/never",
              ("--set", "total=3"): "--set total=3: unknown key 'total'"}  # fmt: skip
    for flags, says in cannot.items():
        assert _train("--genome", str(genome), "--out", str(tmp_path / "never"), *flags) == 2
        assert says in capsys.readouterr().err and not (tmp_path / "never").exists()
    assert _train("--resume", str(out)) == 1  # finished: nothing to go on with, unless extended

    # extended twice from the same folder: the same bits
    twin = tmp_path / "twin"
    shutil.copytree(out, twin)
    assert _train("--resume", str(out), "--steps", str(4 * BATCH)) == 0
    assert _train("--resume", str(twin), "--steps", str(4 * BATCH)) == 0
    assert _sha(out / "checkpoint.pt") == _sha(twin / "checkpoint.pt") != finished
    result = _strict(out / "result.json")  # no NaN, whatever the body did
    assert result["finished"] and result["iterations"] == 4 and result["env_steps"] == 4 * BATCH
    rates = [float(row["learning_rate"]) for row in csv.DictReader((out / "curve.csv").open())]
    schedule = [1e-4 * (1 - i / 2) for i in range(2)] + [1e-4 * (1 - i / 4) for i in (2, 3)]
    assert rates == pytest.approx(schedule)  # from where the new budget puts it, to 0 at its end

    # TensorBoard went on where the first start wrote, with no --tensorboard given again
    events = EventAccumulator(str(board / out.name), size_guidance={"scalars": 0})
    events.Reload()
    steps = [event.step for event in events.Scalars("rollout/ep_len_mean")]
    assert steps == [BATCH * k for k in range(1, 5)]
    assert [e.step for e in events.Scalars("rollout/episodes")] == steps

    # a value that is no number is written null
    summary = folder.settings()  # any model will do for the settings
    from derl.lifetime import LifetimeResult

    values = {**{k: v for k, v in result.items() if k in LifetimeResult.model_fields}}
    values["cost_of_work"] = math.nan
    folder.write_result(summary.ppo, LifetimeResult(**values), 4, True)
    assert _strict(out / "result.json")["cost_of_work"] is None


def test_a_folder_stopped_before_its_first_save_goes_on_from_the_beginning(
    quadruped: Genome, tmp_path: Path, handlers: None
) -> None:
    """A second Ctrl-C at once, before any save: the folder holds its body and settings, and
    `--resume` trains from the beginning to the bits of a training never stopped."""
    genome, out, whole = tmp_path / "body.json", tmp_path / "stopped", tmp_path / "whole"
    genome.write_text(quadruped.model_dump_json())
    assert _train("--genome", str(genome), "--out", str(whole), "--envs", "8", "--steps",
                  str(2 * BATCH)) == 0  # fmt: skip
    out.mkdir()
    for name in ("genome.json", "body.xml", "training.json"):
        shutil.copy(whole / name, out / name)
    assert _train("--genome", str(genome), "--out", str(out)) == 2  # a stopped training's folder
    assert _train("--resume", str(out)) == 0
    assert _sha(out / "checkpoint.pt") == _sha(whole / "checkpoint.pt")


def test_a_second_signal_never_cuts_a_save(handlers: None) -> None:
    said: list[str] = []
    stop = Stop(said.append)
    stop.install()
    signal.raise_signal(signal.SIGTERM)
    assert stop.event.is_set()
    with stop.saving():
        signal.raise_signal(signal.SIGINT)  # the save goes on; the training stops after it
    assert said[-1] == "SIGINT: stopping once this save is written"
    with pytest.raises(KeyboardInterrupt):
        signal.raise_signal(signal.SIGINT)


def test_a_ctrl_c_before_the_training_began_leaves_nothing(
    quadruped: Genome, tmp_path: Path
) -> None:
    """The genome is read from a pipe: the Ctrl-C comes while `derl train` waits for it."""
    pipe, out = tmp_path / "body.json", tmp_path / "never"
    os.mkfifo(pipe)
    argv = derl_argv("train", "--genome", str(pipe), "--out", str(out))
    with subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) as run:
        with pipe.open("w") as writer:  # opened once derl train opens it to read
            run.send_signal(signal.SIGINT)
            threading.Event().wait(0.5)  # the handler runs while the read waits
            writer.write(quadruped.model_dump_json())
        _, stderr = run.communicate(timeout=120)
    assert run.returncode == 130, stderr
    assert stderr.strip().splitlines()[-1] == (
        "derl: stopped before the training began: nothing written"
    )
    assert "Traceback" not in stderr and not out.exists()
