"""A run's results watched: `derl rollout` of a real run's best/ folder with a video, its best
bodies drawn, the gaits `derl report` films from the run's checkpoints, and the one line for a
folder without a body."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest
from nodes_fixtures import REPO, Processes, derl_argv, write_profile
from PIL import Image

from derl.nodes.cli.main import main
from derl.replay import Trained

# one process runs them all: `tiny_run` is made once (under `-n 2` each process made its own)
pytestmark = pytest.mark.xdist_group(name="replay")


def frames(gif: Path) -> int:
    with Image.open(gif) as image:
        return image.n_frames


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A finished `derl run` of 3 bodies (its best/ folders, checkpoints and journal)."""
    base = tmp_path_factory.mktemp("tiny")
    processes = Processes(base / "logs")
    argv = derl_argv("run", "--profile", str(write_profile(base / "profile.yaml")),
                     "--run-dir", str(base / "run"), "--port", "0")  # fmt: skip
    try:
        code = processes.finish(processes.start("run", argv), timeout=180)
    finally:
        processes.close()
    assert code == 0, processes.log("run")
    return base / "run"


def test_rollout_of_a_runs_best_body(tiny_run: Path, tmp_path: Path) -> None:
    (best,) = (tiny_run / "best").glob("01-*")
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


def test_the_best_bodies_are_drawn(tiny_run: Path, tmp_path: Path) -> None:
    """`make run`'s picture: the best/ folders hold settings beside the genomes."""
    picture = tmp_path / "best.png"
    drawn = subprocess.run(
        derl_argv("unimal", "render", str(tiny_run / "best"), "--out", str(picture)),
        capture_output=True, text=True, timeout=120, cwd=REPO,
    )  # fmt: skip
    assert drawn.returncode == 0, drawn.stderr
    with Image.open(picture) as image:
        assert image.size[0] > 320  # a grid of the 3 bodies


def test_report_films_the_best_gaits(tiny_run: Path, tmp_path: Path) -> None:
    out = tmp_path / "report"
    report = subprocess.run(
        derl_argv("report", str(tiny_run), "--out", str(out), "--pictures", "0", "--gaits", "2",
                  "--processes", "1", "--stability-sample", "1"),
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
