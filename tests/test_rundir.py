"""The run directory's lock, contended by real processes, and writes that a kill cannot tear."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from derl.nodes.runtime.rundir import LOCK_FILE, RunDirLocked, lock_run_dir, write_atomic
from derl.nodes.testing.waiting import wait_until


def _python(code: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-c", textwrap.dedent(code)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def _hold_lock(run_dir: Path) -> subprocess.Popen:
    holder = _python(f"""
        import sys, time
        from derl.nodes.runtime.rundir import lock_run_dir
        with lock_run_dir({str(run_dir)!r}):
            print("locked", flush=True)
            time.sleep(120)
    """)
    assert holder.stdout is not None and holder.stdout.readline() == "locked\n"
    return holder


def test_a_second_process_is_refused_and_told_who_holds_the_lock(tmp_path: Path) -> None:
    run_dir = tmp_path / "run"
    holder = _hold_lock(run_dir)
    try:
        with pytest.raises(RunDirLocked) as refused, lock_run_dir(run_dir):
            pass
        message = str(refused.value)
        assert f"pid {holder.pid}" in message and socket.gethostname() in message
        assert str(run_dir) in message and "\n" not in message
    finally:
        holder.kill()
        holder.wait(timeout=10)
    with lock_run_dir(run_dir):  # a killed holder leaves no stale lock
        assert f'"pid": {os.getpid()}' in (run_dir / LOCK_FILE).read_text()
    with lock_run_dir(run_dir):  # released at the end of the block
        pass


def test_the_lock_is_held_until_the_block_ends(tmp_path: Path) -> None:
    with lock_run_dir(tmp_path / "run"):
        contender = _python(f"""
            from derl.nodes.runtime.rundir import RunDirLocked, lock_run_dir
            try:
                with lock_run_dir({str(tmp_path / "run")!r}):
                    print("acquired")
            except RunDirLocked as error:
                print("refused:", error)
        """)
        out, _ = contender.communicate(timeout=30)
    assert out.startswith("refused:") and f"pid {os.getpid()}" in out


def test_write_atomic_replaces_the_file(tmp_path: Path) -> None:
    target = tmp_path / "summary.json"
    write_atomic(target, "first\n")
    write_atomic(target, b"second\n")
    assert target.read_text() == "second\n"
    assert [p.name for p in tmp_path.iterdir()] == ["summary.json"]  # no temporary file left
    assert target.stat().st_mode & 0o777 == 0o666 & ~_umask()


def test_a_write_killed_before_its_rename_leaves_the_old_file_whole(tmp_path: Path) -> None:
    target = tmp_path / "summary.json"
    write_atomic(target, "old " * 1000)
    writer = _python(f"""
        import os, signal
        from derl.nodes.runtime import rundir
        rundir.os.fsync = lambda fd: os.kill(os.getpid(), signal.SIGKILL)  # die at the sync
        rundir.write_atomic({str(target)!r}, "new " * 100_000)
    """)
    writer.wait(timeout=30)
    assert writer.returncode == -signal.SIGKILL
    assert target.read_text() == "old " * 1000
    assert len(list(tmp_path.glob(".summary.json.*.tmp"))) == 1  # the new data went elsewhere


def test_writes_killed_at_any_moment_never_leave_a_part(tmp_path: Path) -> None:
    target = tmp_path / "data.bin"
    size = 4 << 20
    for attempt in range(4):
        writer = _python(f"""
            from derl.nodes.runtime.rundir import write_atomic
            print("writing", flush=True)
            k = 0
            while True:
                write_atomic({str(target)!r}, bytes([97 + k % 2]) * {size})
                k += 1
        """)
        assert writer.stdout is not None and writer.stdout.readline() == "writing\n"
        wait_until(target.exists, 30, "the first write")
        time.sleep(0.05 + 0.07 * attempt)
        writer.send_signal(signal.SIGKILL)
        writer.wait(timeout=10)
        data = target.read_bytes()
        assert len(data) == size and data in (b"a" * size, b"b" * size)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask
