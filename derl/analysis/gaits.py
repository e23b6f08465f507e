"""The best bodies' gaits for the report: a short looping GIF of each body's trained policy,
replayed (`derl.replay`) from its run's checkpoint in the run's world."""

from __future__ import annotations

import logging
from pathlib import Path

from derl.analysis.page import Gait
from derl.analysis.records import Body, RunLog
from derl.envs.video import write_video
from derl.replay import NotTrained, Trained, play

log = logging.getLogger("derl.analysis")

CLIP_STEPS = 150
"""Control steps of a clip at most: 3 s of simulated time, 6 s played."""
CLIP_SIZE = (320, 240)


def write_gaits(
    ranked: list[tuple[RunLog, Body]], count: int, out: Path, notes: list[str]
) -> list[Gait]:
    """Clips of the first `count` bodies of `ranked` that have a checkpoint, written to `out`;
    what could not be filmed goes to `notes`."""
    gaits: list[Gait] = []
    if count == 0:
        return gaits
    for run, body in ranked:
        if len(gaits) == count:
            break
        checkpoint = None if run.checkpoints is None else run.checkpoints / f"{body.id}.pt"
        if checkpoint is None or body.genome is None or not checkpoint.is_file():
            continue
        log.info("filming %s/%s", run.name, body.id)
        try:
            trained = Trained.of(body.genome, run.world, checkpoint.read_bytes())
            (episode,) = play(trained, 1, episode_steps=CLIP_STEPS, film=CLIP_SIZE)
            path = out / f"gait-{run.name}-{body.id}.gif"
            write_video(path, episode.frames)
        except (OSError, NotTrained) as error:
            notes.append(f"the gait of {run.name}/{body.id} could not be filmed: {error}")
            continue
        except RuntimeError as error:  # no offscreen OpenGL: no other body can be filmed
            notes.append(f"the gaits could not be filmed: {error}")
            break
        gaits.append(Gait(file=path.name, label=f"{run.name}/{body.id}: {body.fitness:.4g}"))
    if len(gaits) < count:
        notes.append(
            f"gaits: {len(gaits)} of the {count} asked for were filmed; a body is filmed from its "
            "checkpoint, which a run directory holds (checkpoints/<id>.pt) and a log alone does not"
        )
    return gaits
