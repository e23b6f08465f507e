"""The coordinator's checkpoint files (`<run dir>/checkpoints/<agent>.pt`), written beside its loop.

A born agent's policy comes inside its FitnessReport; one thread writes it to a temporary file
and renames it into place, so a file that exists is whole. File system calls release the GIL, so
the writes run in parallel with the coordinator's loop instead of inside it (measured: creating
a file is the largest single cost of an assignment on a busy machine). `save` returns a future;
the coordinator acknowledges a report only once its checkpoint is on disk.
"""

from __future__ import annotations

from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

FOLDER = "checkpoints"


class CheckpointFiles:
    def __init__(self, run_dir: Path) -> None:
        self.folder = Path(run_dir) / FOLDER
        self.folder.mkdir(parents=True, exist_ok=True)
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="checkpoints")

    def path(self, agent: str) -> Path:
        return self.folder / f"{agent}.pt"

    def save(self, agent: str, checkpoint: bytes) -> Future[None]:
        """Write `agent`'s checkpoint in the background; the future says when it is on disk."""
        return self._pool.submit(self._write, agent, checkpoint)

    def _write(self, agent: str, checkpoint: bytes) -> None:
        tmp = self.folder / f"{agent}.pt.tmp"
        tmp.write_bytes(checkpoint)
        tmp.replace(self.path(agent))

    def close(self) -> None:
        """Wait for the writes under way; closing twice is harmless."""
        self._pool.shutdown(wait=True)
