"""Benchmark of filming (`derl rollout --video`, the report's gaits); prints JSON.

Per world (FT, VT, MVT), the 6-limb reference body, one copy under random actions, offscreen
(``MUJOCO_GL``, egl by default): the time of one frame of `FrameRecorder` (posing the dressed
set, rendering 480x360, reading the pixels back), of one environment step, and, interleaved in
the same run, of rendering the environment's own model as it is (no scenery, the whole
heightfield: what filming cost before the set drew a patch of it); for worlds with terrain, the
time of a frame that moves the patch (cut, coarse terrain rewritten, both sent to the renderer;
it moves every 3 m the body walks). Wall-clock
and CPU time (all threads: Mesa's llvmpipe renders on every core) per frame, medians over
repeats.
Run: python bench/video.py [--repeats 5] [--frames 40]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from collections.abc import Callable

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco
import numpy as np
from bodies import reference_body

from derl.envs import make_env
from derl.envs.video import FrameRecorder

WIDTH, HEIGHT = 480, 360


def _ms(run: Callable[[], object], n: int) -> tuple[float, float]:
    """(wall, CPU) milliseconds per call of `run`, over `n` calls."""
    wall, cpu = time.perf_counter(), time.process_time()
    for _ in range(n):
        run()
    return (
        1000 * (time.perf_counter() - wall) / n,
        1000 * (time.process_time() - cpu) / n,
    )


def bench_world(world: str, repeats: int, frames: int) -> dict[str, object]:
    env = make_env(reference_body(6), world, num_envs=1, seed=0)
    env.reset(0)
    rng = np.random.default_rng(0)
    recorder = FrameRecorder(env, WIDTH, HEIGHT)
    terrains = getattr(env.task.arena, "terrains", None)
    plain_model = env.model if terrains is None else terrains.models[0]
    plain = mujoco.Renderer(plain_model, HEIGHT, WIDTH)
    plain_data = mujoco.MjData(plain_model)
    camera = recorder.camera

    def step() -> None:
        env.step(rng.uniform(-1, 1, (1, env.action_dim)))

    def plain_frame() -> None:
        env.batch.get_data(0, plain_data)
        mujoco.mj_forward(plain_model, plain_data)
        plain.update_scene(plain_data, camera)
        plain.render()

    def move_patch() -> None:  # and a frame
        recorder.set.patch_at[:] = np.inf
        recorder.frame()

    step()
    recorder.frame()
    plain_frame()  # warm-up: textures and the heightfield sent once
    samples: dict[str, list[tuple[float, float]]] = {"frame": [], "step": [], "plain": []}
    if terrains is not None:
        samples["patch_move"] = []
    for _ in range(repeats):
        samples["step"].append(_ms(step, frames))
        samples["frame"].append(_ms(recorder.frame, frames))
        samples["plain"].append(_ms(plain_frame, max(frames // 4, 1)))
        if terrains is not None:
            samples["patch_move"].append(_ms(move_patch, max(frames // 4, 1)))
    recorder.close()
    plain.close()
    result: dict[str, object] = {"world": world}
    for name, values in samples.items():
        result[f"{name}_ms"] = round(statistics.median(w for w, _ in values), 2)
        result[f"{name}_cpu_ms"] = round(statistics.median(c for _, c in values), 2)
    result["frame_vs_plain"] = round(result["frame_ms"] / result["plain_ms"], 2)  # type: ignore[operator]
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--frames", type=int, default=40)
    args = parser.parse_args()
    results = [bench_world(world, args.repeats, args.frames) for world in ("ft", "vt", "mvt")]
    print(
        json.dumps(
            {"size": [WIDTH, HEIGHT], "gl": os.environ["MUJOCO_GL"], "worlds": results}, indent=2
        )
    )


if __name__ == "__main__":
    main()
