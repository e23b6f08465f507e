"""Benchmark of the batched environments; prints JSON.

Per world (FT, VT, MVT) and body (6 and 10 limbs), on one core, medians over repeats with the
two measurements interleaved, all in CPU time of this process (on a shared machine the wall
clock also counts other processes' turns on the core): the raw physics rate (the same
`mujoco.batch.Batch` stepping 4 substeps per control step, nothing else: the ceiling), the
environment's rate with observations, rewards, endings and resets (random actions in [-1, 1],
episodes ending as they do), their ratio, the time the heightmap lookups take per environment
step (timed in a separate run, as they run between physics steps: with cold caches), and
``physics_share``, the share of the environment's (wall) time spent in MuJoCo (its steps and the
forward passes of the copies it resets): where resets change the physics (MVT's box, placed
anew, slides and settles before it sleeps) the raw rate, without resets, is not the physics the
environment runs, and this share is the ratio to it. Random bodies seldom leave the start
area; for worlds with a heightmap, ``ratio_uneven`` and ``heightmap_uneven_ms_per_step`` are
the ratio and the lookup time with every heightmap read point by point, as for bodies walking
over obstacles. Then the cost of a new VT terrain (at a reset, and all of it) against the cost
of an episode, and where the first obstacle lies over the episodes of a VT rollout.
Run: python bench/envs.py [--repeats 5] [--steps 300]
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import mujoco
import numpy as np
from bodies import reference_body

from derl.envs import UnimalEnv, make_env


def _rate(run: Callable[[int], None], steps: int, copies: int) -> float:
    start = time.process_time()
    run(steps)
    return steps * copies / (time.process_time() - start)


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
    terrain = hasattr(env.task.arena, "grid") and env.task.arena.grid is not None  # a heightmap
    raw, full, uneven, share = [], [], [], []
    for _ in range(repeats):
        env.reset(1)
        raw.append(_rate(physics, steps, env.num_envs))
        env.reset(1)
        physics_s, wall = env.physics_s, time.perf_counter()
        full.append(_rate(environment, steps, env.num_envs))
        share.append((env.physics_s - physics_s) / (time.perf_counter() - wall))
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
        "physics_share": round(statistics.median(share), 3),
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
    terrains = env.task.arena.terrains
    terrains.heightmap = lambda xy, yaw, which=None: terrains.lookup(
        terrains.vertices(xy, which), yaw
    )
    try:
        yield
    finally:
        del terrains.heightmap


def _heightmap_ms(env: UnimalEnv, environment: Callable[[int], None], steps: int) -> float:
    """Milliseconds per environment step spent in heightmap lookups (all of a step's calls)."""
    terrains, spent = env.task.arena.terrains, [0.0]
    lookup = terrains.heightmap

    def timed(*args: object) -> np.ndarray:
        start = time.process_time()
        heightmap = lookup(*args)
        spent[0] += time.process_time() - start
        return heightmap

    terrains.heightmap = timed
    env.reset(1)
    environment(steps)
    terrains.heightmap = lookup
    return spent[0] * 1e3 / steps


def bench_terrain(repeats: int) -> dict[str, float]:
    """The cost of a new VT terrain for one copy at a reset: planned, its heightmap flags set
    (`TerrainStack.renew`), then written (into the height stack and the copy's heightfield) where
    a body at the spawn point can touch or see it; and the cost of writing all of it."""
    env = make_env(reference_body(6), "vt", num_envs=1, seed=0)
    terrains, rng, one = env.task.arena.terrains, np.random.default_rng(0), np.zeros(1, np.intp)
    spawn = np.array([env.task.spawn])
    reset, whole = [], []
    for _ in range(repeats * 10):
        start = time.process_time()
        terrains.renew(one, rng)
        terrains.ground(spawn, one)
        reset.append(time.process_time() - start)
        cols, low, high = terrains.written[0].tolist()
        start = time.process_time()
        terrains.complete(0)
        whole.append(time.process_time() - start + reset[-1])
    return {
        "vt_terrain_at_reset_ms_median": round(statistics.median(reset) * 1e3, 3),
        "vt_terrain_whole_ms_median": round(statistics.median(whole) * 1e3, 3),
        "vt_share_written_at_reset": round(cols * (high - low) / terrains.padded[0].size, 3),
    }


def first_obstacles(limbs: int, steps: int) -> dict[str, object]:
    """Where the first obstacle lies (m ahead of the spawn) over the episodes the copies of a
    VT rollout of random actions start: the share of episodes at each distance."""
    env = make_env(reference_body(limbs), "vt", num_envs=32, seed=0)
    env.reset(0)
    terrains, rng = env.task.arena.terrains, np.random.default_rng(1)
    starts = [terrains.first_obstacle.copy()]
    lengths = []
    for _ in range(steps):
        result = env.step(rng.uniform(-1, 1, (env.num_envs, env.action_dim)))
        done = result.terminated | result.truncated
        starts.append(terrains.first_obstacle[done])
        lengths.append(np.count_nonzero(done))
    ahead = np.round(np.concatenate(starts) - env.task.spawn[0], 3)
    values, counts = np.unique(ahead, return_counts=True)
    return {
        "limbs": limbs,
        "episodes": int(counts.sum()),
        "mean_episode_steps": round(steps * env.num_envs / max(sum(lengths), 1), 1),
        "share_by_metres_ahead": {
            f"{v:g}": round(int(c) / int(counts.sum()), 3)
            for v, c in zip(values, counts, strict=True)
        },
    }


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
    terrain["first_obstacles"] = episodes = first_obstacles(6, 1000)
    vt = next(r for r in results if r["world"] == "vt")  # the 6-limb body
    episode_ms = 1000 * episodes["mean_episode_steps"] / vt["env_steps_per_s"]  # one copy's
    terrain["vt_episode_ms_per_copy"] = round(episode_ms, 2)
    terrain["vt_terrain_at_reset_share_of_an_episode"] = round(
        terrain["vt_terrain_at_reset_ms_median"] / episode_ms, 3
    )
    print(json.dumps({"threads": 1, "copies": 32, "worlds": results, "terrain": terrain}, indent=2))


if __name__ == "__main__":
    main()
