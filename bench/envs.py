"""Benchmark of the batched environments; prints JSON.

Per world (FT, VT, MVT) and body (6 and 10 limbs), on one core, medians over repeats with the
two measurements interleaved: the raw physics rate (the same `mujoco.batch.Batch` stepping 4
substeps per control step, nothing else: the ceiling), the environment's rate with observations,
rewards, endings and resets (random actions in [-1, 1], episodes ending as they do), their
ratio, the time the heightmap lookups take per environment step (timed in a separate run, as
they run between physics steps: with cold caches), and the cost of one new terrain against the
cost of one episode. Random bodies seldom leave the flat start area, where heightmaps are zeros
without reading the terrain; for worlds with terrain, ``ratio_uneven`` and
``heightmap_uneven_ms_per_step`` are the ratio and the lookup time with every heightmap read
point by point, as for bodies walking over obstacles.
Run: python bench/envs.py [--repeats 5] [--steps 300]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import mujoco
import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from bodies import reference_body

from derl.envs import UnimalEnv, make_env
from derl.envs.terrain import TerrainConfig, generate_terrain


def _rate(run, steps: int, copies: int) -> float:
    start = time.perf_counter()
    run(steps)
    return steps * copies / (time.perf_counter() - start)


def bench_world(world: str, limbs: int, repeats: int, steps: int) -> dict[str, object]:
    env = make_env(reference_body(limbs), world, num_envs=32, seed=0)
    env.reset(0)
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1, 1, (steps, env.num_envs, env.action_dim)).astype(np.float32)

    def physics(n: int) -> None:
        for t in range(n):
            env.ctrl[:] = actions[t]
            env.batch.step(nstep=4, stage=mujoco.mjtStage.mjSTAGE_VEL)

    def environment(n: int) -> None:
        for t in range(n):
            env.step(actions[t])

    env.reset(0)
    environment(20)  # warm-up
    terrain = hasattr(env.task, "terrains")
    raw, full, uneven = [], [], []
    for _ in range(repeats):
        env.reset(1)
        raw.append(_rate(physics, steps, env.num_envs))
        env.reset(1)
        full.append(_rate(environment, steps, env.num_envs))
        if terrain:
            with _uneven(env):
                env.reset(1)
                uneven.append(_rate(environment, steps, env.num_envs))
    result = {
        "world": world,
        "limbs": limbs,
        "motors": env.action_dim,
        "raw_physics_steps_per_s": round(statistics.median(raw)),
        "env_steps_per_s": round(statistics.median(full)),
        "ratio": round(statistics.median(f / r for f, r in zip(full, raw, strict=True)), 3),
        "terrains_generated": getattr(getattr(env.task, "terrains", None), "generated", 0),
    }
    if terrain:
        result["ratio_uneven"] = round(
            statistics.median(u / r for u, r in zip(uneven, raw, strict=True)), 3
        )
        result["heightmap_ms_per_step"] = round(_heightmap_ms(env, environment, steps), 3)
        with _uneven(env):
            result["heightmap_uneven_ms_per_step"] = round(
                _heightmap_ms(env, environment, steps), 3
            )
    return result


@contextmanager
def _uneven(env: UnimalEnv) -> Iterator[None]:
    """Every heightmap read point by point, as if no head stood above level ground."""
    terrains = env.task.terrains
    terrains.heightmap = lambda xy, yaw, which=None: terrains.lookup(
        terrains.vertices(xy, which), yaw
    )
    try:
        yield
    finally:
        del terrains.heightmap


def _heightmap_ms(env: UnimalEnv, environment: Callable[[int], None], steps: int) -> float:
    """Milliseconds per environment step spent in heightmap lookups (all of a step's calls)."""
    terrains, spent = env.task.terrains, [0.0]
    lookup = terrains.heightmap

    def timed(*args: object) -> np.ndarray:
        start = time.perf_counter()
        heightmap = lookup(*args)
        spent[0] += time.perf_counter() - start
        return heightmap

    terrains.heightmap = timed
    env.reset(1)
    environment(steps)
    terrains.heightmap = lookup
    return spent[0] * 1e3 / steps


def bench_terrain(repeats: int) -> dict[str, float]:
    config = TerrainConfig.variable()
    rng = np.random.default_rng(0)
    times = []
    for _ in range(repeats * 5):
        start = time.perf_counter()
        generate_terrain(config, rng).hfield()
        times.append(time.perf_counter() - start)
    return {"vt_terrain_generation_ms_median": round(statistics.median(times) * 1e3, 2)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--steps", type=int, default=300)
    args = parser.parse_args()
    results = [
        bench_world(world, limbs, args.repeats, args.steps)
        for world in ("ft", "vt", "mvt")
        for limbs in (6, 10)
    ]
    terrain = bench_terrain(args.repeats)
    episode_ms = 1000 * 32 / next(r for r in results if r["world"] == "vt")["env_steps_per_s"]
    terrain["full_vt_episode_ms_per_copy"] = round(episode_ms * 1000 / 32, 1)
    print(json.dumps({"threads": 1, "copies": 32, "worlds": results, "terrain": terrain}, indent=2))


if __name__ == "__main__":
    main()
