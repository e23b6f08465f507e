"""A run directory's files beside its journal: what the run is, what it started from, what it left.

- `profile.json`: the run's settings, saved at its start; a resumed run keeps them (the code's
  defaults may have changed since) and refuses another profile, world or seed; `derl run
  --extend` raises its total (`save_config`).
- `initial_population.json`: the initial bodies, a fact of the run (drawing them again is slow).
- At the end, `best/NN-<agent>/` for the best bodies (trained-agent folders,
  `derl.agent_folder`: genome, MJCF, checkpoint, the world and PPO settings: what `derl rollout`
  needs) and `summary.json` (the settings, births, failures, the best and every evaluation).

Every file is written whole or not at all (`write_atomic`).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

from pydantic import ValidationError

from derl.agent_folder import AgentFolder, TrainingSettings
from derl.evolution import EvolutionConfig
from derl.nodes.coordinator.run.state import EvolutionState
from derl.nodes.errors import Refused
from derl.nodes.runtime.checkpoints import CheckpointFiles
from derl.nodes.runtime.rundir import write_atomic
from derl.rl.config import SAVED
from derl.unimal import Genome
from derl.validation import problems

log = logging.getLogger("derl.coordinator")

PROFILE_FILE = "profile.json"
INITIAL_FILE = "initial_population.json"
BEST_DIR = "best"
SUMMARY_FILE = "summary.json"


def run_config(run_dir: Path, given: EvolutionConfig) -> EvolutionConfig:
    """The run's configuration: the one saved with it when it resumes, else `given`, saved now;
    `Refused` when the saved one is not valid or of another profile, world or seed."""
    saved = saved_config(run_dir)
    if saved is None:
        save_config(run_dir, given)
        return given
    if (saved.name, saved.world, saved.seed) != (given.name, given.world, given.seed):
        raise Refused(
            f"{run_dir} holds a run of profile {saved.name} in {saved.world} with "
            f"seed {saved.seed}, not {given.name} in {given.world} with seed {given.seed}; "
            "resume it with the same profile and seed or use a new --run-dir"
        )
    if saved != given:
        changed = sorted(k for k in type(given).model_fields if getattr(saved, k) !=
                         getattr(given, k))  # fmt: skip
        log.warning("resuming with the run's saved settings (%s differ from the profile's "
                    "today)", ", ".join(changed))  # fmt: skip
    return saved


def saved_config(run_dir: Path) -> EvolutionConfig | None:
    """The settings saved with the run in `run_dir` (None: no run began there); `Refused` when
    they are not valid."""
    path = run_dir / PROFILE_FILE
    if not path.exists():
        return None
    try:
        return EvolutionConfig.model_validate_json(path.read_text(), context=SAVED)
    except ValidationError as error:
        raise Refused(f"{path} is not a valid run configuration: {problems(error)}") from None


def save_config(run_dir: Path, config: EvolutionConfig) -> None:
    """Save `config` as the settings of the run in `run_dir`."""
    run_dir.mkdir(parents=True, exist_ok=True)
    write_atomic(run_dir / PROFILE_FILE, config.model_dump_json(indent=2) + "\n")


def read_initial_population(run_dir: Path) -> list[Genome] | None:
    """The initial bodies, if this run drew them before (else `Evolution` draws them)."""
    path = run_dir / INITIAL_FILE
    if not path.exists():
        return None
    return [Genome.model_validate(g) for g in json.loads(path.read_text())]


def save_initial_population(run_dir: Path, bodies: list[Genome]) -> None:
    """Keep the initial bodies, unless they are kept already."""
    path = run_dir / INITIAL_FILE
    if not path.exists():
        write_atomic(path, json.dumps([genome.model_dump() for genome in bodies]))


def write_results(
    run_dir: Path,
    run: str,
    config: EvolutionConfig,
    state: EvolutionState,
    checkpoints: CheckpointFiles,
) -> None:
    """The best bodies (genome, MJCF, checkpoint, the run's settings) and a summary."""
    evolution = state.evolution
    ranked = state.best()
    settings = TrainingSettings(task=config.world, ppo=config.training_ppo())
    for rank, member in enumerate(ranked[: max(config.eval_top, 3)]):
        folder = AgentFolder(run_dir / BEST_DIR / f"{rank + 1:02d}-{member.agent}")
        folder.path.mkdir(parents=True, exist_ok=True)
        folder.write_body(evolution.genomes[member.agent])
        folder.write_settings(settings)
        checkpoint = checkpoints.path(member.agent)
        if checkpoint.exists():
            folder.write_checkpoint(checkpoint.read_bytes())
    summary = {
        "run": run,
        "profile": config.model_dump(),
        "born": len(evolution.born),
        "fingerprint": state.fingerprint(),
        "failed": sorted(state.failed),
        "audited": len(state.checked),
        "quarantined": {
            q.node: {"caught_at": q.agent, "retrained": list(q.retrain)}
            for q in state.quarantined.values()
        },
        "best": [vars(m) for m in ranked[:10]],
        "evaluations": [r.model_dump(exclude={"curve"}) for r in state.evaluations.values()],
    }
    write_atomic(run_dir / SUMMARY_FILE, json.dumps(summary, indent=2, default=str))
