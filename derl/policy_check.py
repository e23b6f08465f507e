"""Whether checkpoint bytes are a policy of a given body in a given world: what a coordinator checks
before it lets a reported training be born (a trainer could otherwise send any bytes, and an
unreadable "checkpoint" became a run's best agent).

A checkpoint passes when it reads (`read_checkpoint`: no pickled code runs) as the network of the
body in the world, every weight and statistic of the right shape and finite: the observation
spaces and the action count are the body's (proprioception and actions from its model) and the
world's (its other observation types), the weights those of `derl.rl.architecture`'s network.
The body's spaces are computed once per body (a few tens of ms: the model in the flat world), the
world's once per world. Nothing here imports torch: a coordinator never does.
"""

from __future__ import annotations

import numpy as np

from derl.envs import EnvConfig, UnimalEnv, make_task
from derl.rl.architecture import parameter_shapes
from derl.rl.checkpoint_format import read_checkpoint
from derl.rl.normalize import ObsNormalizer
from derl.unimal import Genome, body_hash

BODY_WORLD = "ft"  # where a body's own spaces are read (a plane: the cheapest world to build)


def policy_problem(data: bytes, genome: Genome, world: str) -> str:
    """Why `data` is not a policy of `genome` in `world` ("" if it is one)."""
    try:
        checkpoint = read_checkpoint(data)
    except Exception as error:  # whatever the archive reader or the format check raise
        return f"the checkpoint does not load ({type(error).__name__})"
    spaces, actions = expected_spaces(genome, world)
    if checkpoint["obs_spaces"] != spaces or checkpoint["action_dim"] != actions:
        return (
            f"the checkpoint's network sees {checkpoint['obs_spaces']} and acts on "
            f"{checkpoint['action_dim']}, the body in {world} {spaces} and {actions}"
        )
    weights, stats = checkpoint["weights"], checkpoint["obs_stats"]
    shapes = {name: weight.shape for name, weight in weights.items()}
    if shapes != parameter_shapes(spaces, actions):
        return "the checkpoint's weights are not its network's"
    try:
        ObsNormalizer(spaces, checkpoint["config"].obs_clip).load_state_dict(stats)
    except (ValueError, KeyError, TypeError) as error:
        return f"the checkpoint's statistics are not its network's ({type(error).__name__})"
    if not all(bool(np.isfinite(array).all()) for array in (*weights.values(), *stats.values())):
        return "the checkpoint holds non-finite numbers"
    return ""


def expected_spaces(genome: Genome, world: str) -> tuple[dict[str, int], int]:
    """The observation spaces and the action count of `genome`'s policy in `world`."""
    key = body_hash(genome)
    if key not in _BODIES:
        if len(_BODIES) >= MAX_BODIES:
            _BODIES.clear()
        env = UnimalEnv(genome, make_task(BODY_WORLD), EnvConfig(num_envs=1))
        _BODIES[key] = env.obs_spaces["proprioception"], env.action_dim
    proprioception, actions = _BODIES[key]
    return {"proprioception": proprioception, **_world_spaces(world, genome)}, actions


MAX_BODIES = 4096
_BODIES: dict[str, tuple[int, int]] = {}  # body_hash -> (proprioception size, actions)
_WORLDS: dict[str, dict[str, int]] = {}  # world -> its other observation types


def _world_spaces(world: str, genome: Genome) -> dict[str, int]:
    """The observation types of `world` other than proprioception (built once, with `genome`)."""
    if world not in _WORLDS:
        spaces = UnimalEnv(genome, make_task(world), EnvConfig(num_envs=1)).obs_spaces
        _WORLDS[world] = {k: v for k, v in spaces.items() if k != "proprioception"}
    return _WORLDS[world]
