"""Shared fixtures (small hand-made bodies with known geometry, a test's node processes) and the
suite's order: the tests marked slow first."""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")  # offscreen frames, as the derl command; before MuJoCo

from collections.abc import Iterator
from pathlib import Path

import pytest
from nodes_fixtures import FullDisk, Processes, free_port

from derl.unimal import Genome, Joint, Limb

# The local run's port (`derl run`'s default, where watchers given no endpoint connect): one of
# this test process's own, never a user's run on 7447 nor another test process's.
os.environ["DERL_LOCAL_PORT"] = str(free_port())

XY = (Joint(axis="x", range=(-30, 60), gear=200), Joint(axis="y", range=(-45, 0), gear=150))


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


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """The tests marked slow first (otherwise in file order): under `make test`'s two processes
    (`-n 2 --dist load`) they start at once on both and the short ones fill the end, instead of a
    long test running alone last."""
    items.sort(key=lambda item: item.get_closest_marker("slow") is None)
