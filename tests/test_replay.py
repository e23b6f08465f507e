"""A run's results watched: `derl rollout` of a real run's best/ folder with a video, its best
bodies drawn, the gaits `derl report` films from the run's checkpoints, and the one line for a
folder without a body."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest
from nodes_fixtures import REPO, SMOKE_RUN, FinishedRun, derl_argv
from PIL import Image

from derl.nodes.cli.main import main
from derl.replay import Trained

pytestmark = SMOKE_RUN  # the run they watch is made once, for other tests too


def frames(gif: Path) -> int:
    with Image.open(gif) as image:
        return image.n_frames


def test_rollout_of_a_runs_best_body(smoke_run: FinishedRun, tmp_path: Path) -> None:
    (best,) = (smoke_run.dir / "best").glob("01-*")
    assert Trained.load(best).task == "ft"  # the run's world, from its saved settings
    video = tmp_path / "best.gif"
    shown = subprocess.run(
        derl_argv("rollout", str(best), "--episodes", "2", "--episode-steps", "40",
                  "--video", str(video)),
        capture_output=True, text=True, timeout=120, cwd=REPO,
    )  # fmt: skip
    assert shown.returncode == 0, shown.stderr
    assert shown.stdout.count("episode ") == 2
    filmed = frames(video)
    printed = "".join(shown.stdout.split())  # rich wraps a long path anywhere, even mid-name
    assert 1 < filmed <= 40 and f"wrote{video}({filmed}frames)" in printed


def test_the_best_bodies_are_drawn(smoke_run: FinishedRun, tmp_path: Path) -> None:
    """`make run`'s picture: the best/ folders hold settings beside the genomes."""
    picture = tmp_path / "best.png"
    drawn = subprocess.run(
        derl_argv("unimal", "render", str(smoke_run.dir / "best"), "--out", str(picture)),
        capture_output=True, text=True, timeout=120, cwd=REPO,
    )  # fmt: skip
    assert drawn.returncode == 0, drawn.stderr
    with Image.open(picture) as image:
        assert image.size[0] > 320  # a grid of the best bodies


def test_report_films_the_best_gaits(smoke_run: FinishedRun, tmp_path: Path) -> None:
    out = tmp_path / "report"
    report = subprocess.run(
        derl_argv("report", str(smoke_run.dir), "--out", str(out), "--pictures", "0",
                  "--gaits", "2", "--processes", "1", "--stability-sample", "1"),
        capture_output=True, text=True, timeout=120, cwd=REPO,
    )  # fmt: skip
    assert report.returncode == 0, report.stderr
    gaits = sorted(out.glob("gait-*.gif"))
    assert len(gaits) == 2 and all(frames(gif) > 1 for gif in gaits)
    page = (out / "index.html").read_text()
    assert all(f'src="{gif.name}"' in page for gif in gaits)


def test_a_folder_without_a_body_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "genome.json").write_text("{}")
    with pytest.raises(SystemExit) as exited:
        main(["rollout", str(tmp_path)])
    assert exited.value.code == 2
    error = capsys.readouterr().err
    assert error.count("\n") == 1 and error.startswith(f"derl: {tmp_path} holds no trained body")
    assert "no checkpoint.pt" in error and "no genome.json" not in error
