"""The actor-critic's parameters by name and shape, without torch: what the state dict of
`derl.rl.network.ActorCritic` holds for a body's observation spaces and action count, and so what
a coordinator checks a reported checkpoint against (`derl.policy_check`) without building the
network (tests/test_ppo.py checks that the two agree).

Per tower (actor, critic), one [size -> HIDDEN -> HIDDEN] MLP per observation type
(`branches.<type>.0` and `.2`: the layers of an `nn.Sequential` with tanh between), and with
several types a fuse layer over their concatenation (`fuse.0`); then the action mean and value
heads and the actions' log-std. A linear layer's weight is (out, in), as torch stores it.
"""

from __future__ import annotations

HIDDEN = 64
"""Width of every hidden layer (paper, appendix B)."""


def parameter_shapes(obs_spaces: dict[str, int], action_dim: int) -> dict[str, tuple[int, ...]]:
    """The name and shape of every parameter of the actor-critic for these spaces."""
    shapes: dict[str, tuple[int, ...]] = {}

    def linear(name: str, inputs: int, outputs: int) -> None:
        shapes[f"{name}.weight"], shapes[f"{name}.bias"] = (outputs, inputs), (outputs,)

    for tower in ("actor", "critic"):
        for key in sorted(obs_spaces):
            linear(f"{tower}.branches.{key}.0", obs_spaces[key], HIDDEN)
            linear(f"{tower}.branches.{key}.2", HIDDEN, HIDDEN)
        if len(obs_spaces) > 1:
            linear(f"{tower}.fuse.0", HIDDEN * len(obs_spaces), HIDDEN)
    linear("mean_head", HIDDEN, action_dim)
    linear("value_head", HIDDEN, 1)
    shapes["log_std"] = (action_dim,)
    return shapes
