"""What the physics engine's version can change: the shipped agents (agents/) acting in their worlds
under MuJoCo 4's defaults and with the defaults that MuJoCo 2.0 did not have turned off; prints
JSON.

MuJoCo 2.0 (the released code's, through `mujoco_py`) cannot be run here, so what can be measured
is what derl's engine does by default that 2.0 did not (`OFF`: joint damping integrated
implicitly by the Euler integrator, several contacts per convex pair, MuJoCo's own convex
collider instead of libccd): per agent and setting, over `--copies` copies for one 1,000-step
episode each (episodes that end early are not restarted), the mean episode sum of the world's
fitness term, the episodes that ended early (falls, the arena's edge), and per control step the
contacts (`ncon`) and constraint rows (`nefc`) at its end, mean over copies and steps.
Run: python bench/engine.py [--copies 16] [--agents ft vt mvt]
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import mujoco
import numpy as np

from derl.envs import EnvConfig, UnimalEnv, make_task
from derl.replay import load_trained

AGENTS = Path(__file__).resolve().parents[1] / "agents"
OFF = (
    mujoco.mjtDisableBit.mjDSBL_EULERDAMP
    | mujoco.mjtDisableBit.mjDSBL_MULTICCD
    | mujoco.mjtDisableBit.mjDSBL_NATIVECCD
)
"""MuJoCo 4's defaults that MuJoCo 2.0 did not have."""


@contextmanager
def _defaults(on: bool) -> Iterator[None]:
    """Environments built inside run with MuJoCo 4's defaults `on`, or with `OFF` off: the flags
    are set on the compiled model before the task copies it for its terrains."""
    index = UnimalEnv._index_model

    def off(env: UnimalEnv) -> None:
        env.model.opt.disableflags |= OFF
        env.set_models([env.model] * env.num_envs)
        index(env)

    if not on:
        UnimalEnv._index_model = off
    try:
        yield
    finally:
        UnimalEnv._index_model = index


def measure(name: str, copies: int, defaults: bool) -> dict[str, object]:
    trained = load_trained(AGENTS / name)
    task = make_task(trained.task)
    with _defaults(defaults):
        env = UnimalEnv(trained.genome, task, EnvConfig(num_envs=copies), seed=1409)
    ncon, nefc = env.batch.bind("ncon"), env.batch.bind("nefc")
    obs = env.reset(1409)
    total = np.zeros(copies)
    alive = np.ones(copies, dtype=bool)
    ended = np.zeros(copies, dtype=bool)
    contacts, rows = [], []
    for _ in range(EnvConfig().episode_steps):
        step = env.step(trained.act(obs))
        obs = step.obs
        total[alive] += step.components[task.fitness_component][alive]
        contacts.append(ncon[alive].mean())
        rows.append(nefc[alive].mean())
        ended |= step.terminated & alive
        alive &= ~(step.terminated | step.truncated)
        if not alive.any():
            break
    return {
        "agent": name,
        "mujoco4_defaults": defaults,
        "fitness": float(total.mean()),
        "fitness_sd": float(total.std(ddof=1)),
        "ended_early": int(ended.sum()),
        "contacts_per_step": float(np.mean(contacts)),
        "rows_per_step": float(np.mean(rows)),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--copies", type=int, default=16)
    parser.add_argument("--agents", nargs="+", default=["ft", "vt", "mvt"])
    args = parser.parse_args()
    results = [
        measure(name, args.copies, defaults) for name in args.agents for defaults in (True, False)
    ]
    print(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
