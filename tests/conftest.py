"""Shared fixtures (small hand-made bodies with known geometry, a test's node processes), the
suite's order (the longest tests first, `xdist_group`s kept together) and the package's bytecode
written once for the `derl` processes the tests start."""

from __future__ import annotations

import compileall
import os
import subprocess

os.environ.setdefault("MUJOCO_GL", "egl")  # offscreen frames, as the derl command; before MuJoCo

from collections.abc import Iterator
from pathlib import Path

import pytest
from nodes_fixtures import REPO, FinishedRun, FullDisk, Processes, derl_argv, free_port

from derl.unimal import Genome, Joint, Limb

# The local run's port (`derl run`'s default, where watchers given no endpoint connect): one of
# this test process's own, never a user's run on 7447 nor another test process's.
os.environ["DERL_LOCAL_PORT"] = str(free_port())

XY = (Joint(axis="x", range=(-30, 60), gear=200), Joint(axis="y", range=(-45, 0), gear=150))


@pytest.fixture(scope="session")
def smoke_run(tmp_path_factory: pytest.TempPathFactory) -> FinishedRun:
    """`derl run --profile smoke` (the README's main job), made once by the test process that
    runs the tests marked `SMOKE_RUN` (nodes_fixtures), which read it and write elsewhere."""
    run_dir = tmp_path_factory.mktemp("smoke") / "smoke-ft"
    argv = derl_argv("run", "--profile", "smoke", "--run-dir", str(run_dir), "--port", "0")
    printed = subprocess.run(argv, capture_output=True, text=True, timeout=600)
    assert printed.returncode == 0, printed.stdout + printed.stderr
    return FinishedRun(run_dir, printed)


@pytest.fixture
def quadruped() -> Genome:
    """A front and a back pair of legs from the head, lower legs on the front pair."""
    return Genome(
        head_density=700,
        limb_density=600,
        limbs=(
            Limb(id=0, paired=True, length=0.3, theta=45, phi=135, joints=XY),
            Limb(id=1, paired=True, length=0.3, theta=135, phi=135, joints=XY[:1]),
            Limb(id=2, parent=0, site="end", paired=True, length=0.2, theta=0, phi=180, joints=XY),
        ),
    )


@pytest.fixture
def procs(tmp_path: Path) -> Iterator[Processes]:
    """The test's child processes (logs in tmp_path/logs), all stopped when it ends."""
    processes = Processes(tmp_path / "logs")
    try:
        yield processes
    finally:
        processes.close()


@pytest.fixture(params=FullDisk.kinds())
def full_disk(tmp_path: Path, request: pytest.FixtureRequest) -> Iterator[FullDisk]:
    """A folder whose writes the test makes fail and work again (`FullDisk`): on a small tmpfs
    where this machine lets a test mount one, and with the writers' file-size limit."""
    disk = FullDisk(tmp_path / "disk", request.param)
    try:
        yield disk
    finally:
        disk.close()


def pytest_configure(config: pytest.Config) -> None:
    if "PYTEST_XDIST_WORKER" not in os.environ:  # once, before `-n`'s processes start
        _compile_the_package()


def _compile_the_package() -> None:
    """The package's bytecode (`__pycache__`, ignored by git), written once for the hundreds of
    `derl` processes the tests start: where PYTHONDONTWRITEBYTECODE is set, as on this suite's
    CI machine, Python never writes it, and every one of them compiled derl's 150 modules again
    (~0.2 s of CPU a start). Python reads it all the same; a file changed since is compiled
    again in memory, as without it. Nothing is said where it cannot be written."""
    for folder in ("derl", "nodes", "messages"):
        compileall.compile_dir(REPO / folder, quiet=2)


@pytest.hookimpl(trylast=True)  # after xdist's, which marks the grouped tests
def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """The suite's order under `make test`'s four processes (`-n 4 --dist loadgroup`, which hands
    out tests in this order, one at a time, to whichever process is free): the longest first, by
    `LONGEST` (seconds under -n 4 on a 2-core machine: only their order counts), then the other
    tests marked slow, then the rest in file order. The long ones start at once on every process
    and the short ones fill the end, instead of a long test running alone last. Tests of one
    `xdist_group` run together on one process (and start before the rest)."""
    items.sort(key=_longest_first)
    _keep_xdist_groups(items)


def _longest_first(item: pytest.Item) -> tuple[int, bool]:
    return -LONGEST.get(f"{item.path.name}::{item.name}", 0), not item.get_closest_marker("slow")


# file::test: seconds each of the longest tests took under `make test` (-n 4) on a 2-core machine
# (rounded: only their order counts), grouped tests aside (those start first in any case).
LONGEST = {
    "test_chaos.py::test_a_run_survives_a_schedule_of_faults": 117,
    "test_readme.py::test_the_readme_python_and_body_commands_run": 109,
    "test_lifetime.py::test_ppo_makes_a_quadruped_walk_forward": 100,
    "test_multihost.py::test_run_survives_a_host_dropping_off": 86,
    "test_study.py::test_a_study_of_two_worlds_from_runs_to_figure_4": 80,
    "test_slurm.py::test_a_job_near_its_time_limit_requeues_itself_and_resumes_the_run": 71,
    "test_launch.py::test_launch_runs_to_the_end_and_restarts_a_killed_trainer": 66,
    "test_reproducible.py::test_the_same_seed_gives_the_same_births_on_any_number_of_"
    "trainers_and_after_crashes[cluster]": 63,
    "test_soak.py::test_a_short_soak_finishes_with_every_child_born_once": 60,
    "test_reproducible.py::test_the_same_seed_gives_the_same_births_on_any_number_of_"
    "trainers_and_after_crashes[window]": 57,
    "test_run_supervisor.py::test_a_stopped_run_prints_the_command_that_resumes_it": 56,
    "test_lifetime.py::test_train_and_rollout_commands": 54,
    "test_study.py::test_a_study_selects_retrains_and_tests_each_body_once": 53,
    "test_slurm.py::test_a_cancelled_trainer_step_is_replaced": 50,
    "test_run_supervisor.py::test_run_restarts_a_killed_trainer_and_a_killed_coordinator": 49,
    "test_distributed.py::test_coordinator_restart_loses_nothing": 46,
    "test_video.py::test_the_camera_follows_the_body_over_an_episode[vt]": 44,
    "test_birth_stream.py::test_a_raw_monitor_sees_exactly_the_journals_births": 40,
    "test_security.py::test_a_report_with_another_body_than_its_job_is_rejected": 39,
    "test_security.py::test_tls_and_per_node_access_control": 39,
    "test_audit.py::test_a_real_trainer_that_inflates_every_report_leaves_the_honest_run": 36,
    "test_watch.py::test_replay_says_when_nobody_heard_it": 33,
    "test_resume.py::test_derl_train_stops_on_sigterm_saving_everything_and_resumes": 32,
    "test_slurm.py::test_a_run_is_one_job_on_two_nodes": 32,
    "test_full_disk.py::test_a_full_disk_stalls_the_coordinator_until_it_has_room[tmpfs]": 30,
    "test_ppo.py::test_ppo_learns_inverted_pendulum": 28,
    "test_resume.py::test_a_training_stopped_and_resumed_ends_with_the_bits_of_one_never_"
    "stopped[mvt]": 27,
    "test_gym_api.py::test_stable_baselines3_trains_a_derl_body": 26,
    "test_reproducible.py::test_the_coordinator_ends_a_run_as_the_released_code_did_on_any_"
    "trainers_and_resumed": 25,
    "test_full_disk.py::test_a_full_disk_stalls_the_coordinator_until_it_has_room[fsize]": 26,
    "test_video.py::test_mvt_shows_the_box_and_its_goal_then_the_goal_from_the_box": 26,
    "test_resume.py::test_a_training_stopped_and_resumed_ends_with_the_bits_of_one_never_"
    "stopped[vt]": 26,
    "test_distributed.py::test_stopped_trainer_is_noticed_within_its_lease": 22,
    "test_inherit.py::test_an_inheriting_evolution_over_zenoh_trains_children_from_their_"
    "parents_weights": 21,
    "test_cli_unimal.py::test_sample_show_render": 20,
    "test_coordinator.py::test_the_state_grows_by_births_not_by_jobs_or_learning_curves": 19,
    "test_reproducible.py::test_training_gives_the_same_bits_in_any_process_first_or_last": 19,
    "test_watch.py::test_watchers_given_no_endpoint_find_the_local_run": 18,
    "test_mcap_tools.py::test_damage_in_the_last_segment_is_damage_for_every_tool": 18,
    "test_watch.py::test_a_birth_never_published_is_asked_for_again[monitor]": 17,
    "test_tensorboard.py::test_the_live_watcher_writes_what_export_writes_and_goes_on_after_"
    "a_restart": 17,
    "test_distributed.py::test_killed_trainer_loses_nothing": 17,
    "test_distributed.py::test_garbage_on_every_key_is_rejected": 17,
    "test_audit.py::test_honest_trainers_give_the_births_of_an_unaudited_run[0.0]": 15,
    "test_study_report.py::test_fig2a_pools_the_top_100_of_3_runs": 14,
    "test_mutations.py::test_a_failed_attempt_draws_a_new_site": 14,
}


def _keep_xdist_groups(items: list[pytest.Item]) -> None:
    """xdist's `--dist loadgroup` learns a test's `xdist_group` from the id its process reports,
    `file::test@group`: its own collection hook sets it as `item._nodeid`, which pytest 9.2 no
    longer reads (the id is `item._id`, a structured `NodeId`), so a group's tests were spread
    over both processes and each ran the group's module fixtures, test_crash.py's recording
    (pytest-dev/pytest-xdist#1386, open). The id xdist meant is set where pytest reads it; a
    no-op where xdist's own setting took (earlier pytest, or once xdist sets the new id)."""
    try:
        from _pytest.nodeid import NodeId
    except ImportError:  # pytest before 9.2: `_nodeid` is the id
        return
    for item in items:
        meant = vars(item).get("_nodeid")
        if isinstance(meant, str) and meant != item.nodeid:
            item._id = NodeId.parse(meant)
