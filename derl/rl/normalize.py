"""Running observation normalisation and return-based reward scaling, as in baselines' VecNormalize.

Observations: only "proprioception" is normalised, (x - running mean) / running std clipped to
±clip, as in the original; heightmap, object and goal observations (metres in the head frame) go
in raw. (A heightmap is exactly zero while a body stays on flat ground: its variance would
collapse to 0 and the first obstacle would read as saturated inputs.) Rewards: divided by the
running std of the discounted return (gamma 0.99) of each copy, clipped to ±clip.

Statistics change only in `update` (observations) or `scale` (rewards); evaluation loads the
saved state and only calls `normalize`, which keeps the statistics frozen. State is a flat dict
of numpy arrays.
"""

from __future__ import annotations

import numpy as np

EPS = 1e-8
"""Added to the variance before the square root."""


class RunningMeanStd:
    """Mean and (population) variance of everything seen so far, merged batch by batch; `std`
    is kept current (it is read every step)."""

    def __init__(self, shape: tuple[int, ...]) -> None:
        self.mean = np.zeros(shape, np.float64)
        self.var = np.ones(shape, np.float64)
        self.count = 0.0
        self.std = np.sqrt(self.var + EPS)

    def update(self, batch: np.ndarray) -> None:
        """Merge a batch whose first axis indexes samples (Chan et al. parallel algorithm), in a
        few ufunc calls: this runs once per step."""
        n = batch.shape[0]
        if n == 0:
            return
        b_mean = np.add.reduce(batch, axis=0, dtype=np.float64)
        b_mean /= n
        dev = np.subtract(batch, b_mean, dtype=np.float64)
        m2 = np.add.reduce(np.square(dev, out=dev), axis=0)  # the batch's sum of squares
        total = self.count + n
        delta = b_mean - self.mean
        m2 += self.var * self.count
        m2 += np.square(delta) * (self.count * n / total)
        self.mean = self.mean + delta * (n / total)
        self.var = m2 / total
        self.count = total
        self.std = np.sqrt(self.var + EPS)

    def state_dict(self) -> dict[str, np.ndarray]:
        return {"mean": self.mean.copy(), "var": self.var.copy(), "count": np.array(self.count)}

    def load_state_dict(self, state: dict[str, np.ndarray]) -> None:
        self.mean = np.array(state["mean"], np.float64).reshape(self.mean.shape)
        self.var = np.array(state["var"], np.float64).reshape(self.var.shape)
        self.count = float(state["count"])
        self.std = np.sqrt(self.var + EPS)


NORMALIZED = "proprioception"
"""The observation type that is normalised; every other type passes through raw."""


class ObsNormalizer:
    """Running normalisation of the proprioception in dict observations."""

    def __init__(self, obs_spaces: dict[str, int], clip: float) -> None:
        self.clip = clip
        self.stats = {
            key: RunningMeanStd((dim,)) for key, dim in obs_spaces.items() if key == NORMALIZED
        }

    def update(self, obs: dict[str, np.ndarray]) -> None:
        for key, rms in self.stats.items():
            rms.update(obs[key])

    def normalize(
        self, obs: dict[str, np.ndarray], out: dict[str, np.ndarray] | None = None
    ) -> dict[str, np.ndarray]:
        """Normalised float32 copy of `obs` (written into `out` when given)."""
        if out is None:
            out = {key: np.empty(x.shape, np.float32) for key, x in obs.items()}
        for key, x in obs.items():
            rms = self.stats.get(key)
            if rms is None:
                out[key][...] = x
            else:  # np.clip without its Python wrappers (this runs once per step)
                z = np.subtract(x, rms.mean)
                z /= rms.std
                np.minimum(np.maximum(z, -self.clip, out=z), self.clip, out=out[key])
        return out

    def state_dict(self) -> dict[str, np.ndarray]:
        return {
            f"{key}/{name}": value
            for key, rms in self.stats.items()
            for name, value in rms.state_dict().items()
        }

    def load_state_dict(self, state: dict[str, np.ndarray]) -> None:
        for key, rms in self.stats.items():
            rms.load_state_dict({name: state[f"{key}/{name}"] for name in ("mean", "var", "count")})


class RewardScaler:
    """Divides rewards by the running std of each copy's discounted return, then clips."""

    def __init__(self, num_envs: int, gamma: float, clip: float) -> None:
        self.gamma = gamma
        self.clip = clip
        self.returns = np.zeros(num_envs, np.float64)
        self.stats = RunningMeanStd(())

    def scale(self, reward: np.ndarray, done: np.ndarray) -> np.ndarray:
        """Update the statistics with this step and return the scaled rewards."""
        self.returns *= self.gamma
        self.returns += reward
        self.stats.update(self.returns)
        self.returns[done] = 0.0
        scaled = np.divide(reward, self.stats.std)
        return np.minimum(np.maximum(scaled, -self.clip, out=scaled), self.clip, out=scaled)

    def state_dict(self) -> dict[str, np.ndarray]:
        """The return statistics and each copy's running discounted return (a training resumed
        goes on with both)."""
        return {**self.stats.state_dict(), "returns": self.returns.copy()}

    def load_state_dict(self, state: dict[str, np.ndarray]) -> None:
        self.stats.load_state_dict(state)
        self.returns = np.array(state["returns"], np.float64).reshape(self.returns.shape)
