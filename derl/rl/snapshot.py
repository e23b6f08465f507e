"""A batched environment's whole state, captured and put back into a fresh copy of it, so that
a training resumed from a checkpoint steps on exactly as the one that wrote it.

`capture(env)` walks the environment's object graph (its attributes and those of the task's
parts, down through lists, tuples and dicts) and keeps every value that can change: arrays,
numbers, the random generators' states, the simulations' state rows (`mujoco.batch.Batch`) and,
of every model a copy runs on, the fields that differ from the environment's compiled model
(terrain heights, collision bits). Configurations (pydantic models), the genome, methods and
the compiled model are not state. An array that lies inside the memory of one kept already (a
view) is not kept twice, and of a large array only the chunks that are not all zero are kept
(terrains are mostly flat).
`restore(env, state)` writes the values into an environment built with the same body, task and
settings: in place where an attribute is an array of the same shape (views of the simulations'
state stay views), as new values elsewhere, then recomputes the simulations' derived quantities
(positions, velocities, sensors) from the restored state, as the last step left them.

MuJoCo keeps the sleep state of bodies allowed to sleep (with `derl.envs.EnvConfig.sleep`:
MVT's box, the test tasks' box and ball) outside the state rows, and lets one set it only
through the simulation: a body asleep is put to sleep again by resetting its copy with the
body's sleep policy "asleep at start" and its resting pose as the model's default; a body still
and counting down to sleep (`mujoco.mjMINAWAKE` substeps) by as many substeps from the restored
state as it has been still, the state rows written back after each. That holds unless the body
touches another (the substeps would move it); `capturable` says whether the state is free of
such bodies now, and `restore` checks that every sleep state came back.

The state is a tree of dicts, lists, strings, numbers and torch tensors, which `torch.load`
reads with ``weights_only=True``.
"""

from __future__ import annotations

import copy
import functools
import importlib
from typing import Any, cast

import mujoco
import mujoco.batch
import numpy as np
import torch
from numpy.lib.array_utils import byte_bounds
from pydantic import BaseModel

KIND = "__kind__"
"""The key of a tagged node of the tree: an object, a tuple, a named tuple, a dict, a numpy
scalar, a large array's chunks, a generator's state, a model's changed fields, the simulations, or
a value already kept (an object seen before, a view of an array kept)."""
STATE_PACKAGE = "derl.envs"
"""Objects of classes from this package are walked into; other objects are not state."""
PACK_BYTES = 1 << 20
"""Arrays of at least this many bytes are kept as their chunks that are not all zero."""
CHUNK = 1024
AWAKE = -(1 + mujoco.mjMINAWAKE)
"""MuJoCo's sleep state of a tree fully awake (`tree_asleep`; >= 0: asleep, in a cycle of
trees; between: awake and still, about to sleep)."""
_SKIP = object()


def capturable(env: Any) -> bool:
    """Whether `restore` can put the state `capture` keeps now back exactly: every body that
    may sleep is awake, asleep on its own (not in a cycle of several), or about to sleep on its
    own (touching no other body)."""
    sleep = _sleep(env)
    if sleep is None:
        return True
    asleep, island = sleep
    trees = np.arange(asleep.shape[1])
    alone = np.array([[np.count_nonzero(row == k) == 1 for k in row] for row in island])
    fine = (asleep == AWAKE) | (asleep == trees) | ((asleep < 0) & ((island < 0) | alone))
    return bool(fine.all())


def capture(env: Any) -> dict[str, Any]:
    """The state of `env` (a `derl.envs.UnimalEnv`) as a tree that `restore` reads."""
    walk = _Capture(env.model)
    state = walk.node(env)
    sleep = _sleep(env)
    return {"env": state, "asleep": None if sleep is None else torch.from_numpy(sleep[0])}


def restore(env: Any, state: dict[str, Any]) -> None:
    """Put `state` (from `capture`) into `env`, a fresh environment of the same body, task and
    settings (built with any seed); `ValueError` where a body's sleep state could not be
    restored (`capturable` was false)."""
    _restore(env, state["env"], env.model)
    batch: mujoco.batch.Batch = env.batch
    if state["asleep"] is not None:
        asleep = state["asleep"].numpy()
        _put_to_sleep(env, asleep)
        now = _sleep(env)
        if now is None or not np.array_equal(now[0], asleep):
            raise ValueError("a body's sleep state in this environment state cannot be restored")
    models = batch.models
    if isinstance(models, tuple):
        batch.set_models(list(models))  # edited in place: set again, as the batch asks
    batch.forward(stage=mujoco.mjtStage.mjSTAGE_VEL)


def _sleep(env: Any) -> tuple[np.ndarray, np.ndarray] | None:
    """MuJoCo's `tree_asleep` and `tree_island` of every copy, (copies, trees) each, where
    bodies may sleep."""
    if not env.model.opt.enableflags & mujoco.mjtEnableBit.mjENBL_SLEEP:
        return None
    datas = [env.batch.get_data(i) for i in range(env.batch.nsim)]
    asleep = np.array([data.tree_asleep for data in datas], np.int32)
    return asleep, np.array([data.tree_island for data in datas], np.int32)


def _put_to_sleep(env: Any, asleep: np.ndarray) -> None:
    """Bring the copies' bodies into the sleep states `asleep` (MuJoCo's `tree_asleep`), the
    copies' state rows unchanged: a body asleep by a reset that starts it asleep where it
    rests; a body about to sleep by as many substeps from the same state as it has been still
    (each counts one, if the body stays still in it, as it did)."""
    batch, model = env.batch, env.model
    rows = batch.state.copy()
    sleeping = np.flatnonzero((asleep >= 0).any(axis=1))
    if len(sleeping):
        before = batch.models  # per copy (a tuple), or one for all: then copies for a while
        shared = not isinstance(before, tuple)
        models = [copy.copy(model) for _ in range(batch.nsim)] if shared else list(before)
        start = mujoco.mj_stateSize(model, mujoco.mjtState.mjSTATE_TIME)
        kept = {i: (models[i].tree_sleep_policy.copy(), models[i].qpos0.copy()) for i in sleeping}
        for i in sleeping.tolist():
            models[i].tree_sleep_policy[asleep[i] >= 0] = mujoco.mjtSleepPolicy.mjSLEEP_INIT
            models[i].qpos0[:] = rows[i, start : start + model.nq]  # asleep where it rests
        batch.set_models(models)
        batch.reset(sleeping, stage=mujoco.mjtStage.mjSTAGE_NONE)
        for k, (policy, qpos0) in kept.items():
            models[k].tree_sleep_policy[:] = policy
            models[k].qpos0[:] = qpos0
        batch.set_models(before if shared else models)
    still = np.where((asleep > AWAKE) & (asleep < 0), asleep - AWAKE, 0).max(axis=1)
    for count in range(1, int(still.max(initial=0)) + 1):
        ids = np.flatnonzero(still >= count)
        batch.state[ids] = rows[ids]
        batch.step(ids, nstep=1, stage=mujoco.mjtStage.mjSTAGE_NONE)
    batch.state[...] = rows


class _Capture:
    """One capture's walk: the objects seen, and the memory of the arrays kept."""

    def __init__(self, base: mujoco.MjModel) -> None:
        self.base = base
        self.seen: set[int] = set()
        self.kept: list[tuple[int, int]] = []  # (low, high) addresses of writeable arrays kept

    def node(self, value: object) -> object:
        """`value`'s node, or `_SKIP` where it is not state (nor a container of only state)."""
        if isinstance(value, np.generic):  # before float: np.float64 is one
            return {KIND: "scalar", "value": torch.from_numpy(np.array(value))}
        if value is None or isinstance(value, bool | int | float | str):
            return value
        if isinstance(value, np.ndarray):
            return self.array(value)
        if isinstance(value, np.random.Generator):
            return {KIND: "rng", "state": value.bit_generator.state}
        if id(value) in self.seen:
            return {KIND: "seen"}
        self.seen.add(id(value))
        if isinstance(value, mujoco.batch.Batch):
            return {KIND: "batch", "state": torch.from_numpy(value.state.copy())}
        if isinstance(value, mujoco.MjModel):
            return {KIND: "model", "fields": self.changed_fields(value)}
        if isinstance(value, list | tuple):
            made_again = isinstance(value, tuple)  # from its items: none left to another's
            items = [
                self.array(item, share=False)
                if made_again and isinstance(item, np.ndarray)
                else self.node(item)
                for item in value
            ]
            if any(item is _SKIP for item in items):
                return _SKIP  # e.g. the task's hooks: methods
            if isinstance(value, list):
                return items
            if type(value) is tuple:
                return {KIND: "tuple", "items": items}
            return {KIND: "named", "class": _name(type(value)), "items": items}
        if isinstance(value, dict):
            return {KIND: "dict", "items": self.entries(value)}
        if _walked(value):
            return {KIND: "object", "attrs": self.entries(vars(value))}
        return _SKIP

    def entries(self, values: dict[str, object]) -> dict[str, object]:
        """The nodes of the entries of `values` that are state."""
        nodes = {key: self.node(value) for key, value in values.items()}
        return {key: node for key, node in nodes.items() if node is not _SKIP}

    def array(self, value: np.ndarray, share: bool = True) -> object:
        """`value`'s node; "seen" where `share` allows and it is a writeable view into an
        array kept (restored in place, it restores the view)."""
        if not value.flags.writeable:
            return _packed(value)
        low, high = byte_bounds(value)
        if share and any(a <= low and high <= b for a, b in self.kept):
            return {KIND: "seen"}
        self.kept.append((low, high))
        return _packed(value)

    def changed_fields(self, model: mujoco.MjModel) -> dict[str, object]:
        return {
            name: self.array(getattr(model, name))
            for name in _field_names()
            if not _same(getattr(model, name), getattr(self.base, name))
        }


def _packed(value: np.ndarray) -> object:
    """A copy of `value`: a tensor, or where large, its chunks of `CHUNK` items that hold a
    non-zero bit (the others are all zero bits: flat terrain)."""
    if value.nbytes < PACK_BYTES:
        return torch.from_numpy(np.array(value))
    flat = np.ascontiguousarray(value).reshape(-1)
    whole = len(flat) // CHUNK * CHUNK
    chunks = flat[:whole].reshape(-1, CHUNK)
    bits = chunks.view(f"u{flat.itemsize}")  # -0.0 and NaN are not zero bits
    used = np.logical_or.reduce(bits != 0, axis=1)
    return {
        KIND: "chunks",
        "used": torch.from_numpy(used),
        "chunks": torch.from_numpy(chunks[used]),
        "tail": torch.from_numpy(flat[whole:].copy()),
        "shape": list(value.shape),
    }


def _unpacked(node: object) -> np.ndarray:
    if isinstance(node, torch.Tensor):
        return node.numpy()
    packed = cast(dict[str, Any], node)  # else a large array's chunks (`_packed`)
    tail = packed["tail"].numpy()
    used = packed["used"].numpy()
    flat = np.zeros(len(used) * CHUNK + len(tail), tail.dtype)
    flat[: len(used) * CHUNK].reshape(-1, CHUNK)[used] = packed["chunks"].numpy()
    flat[len(used) * CHUNK :] = tail
    return flat.reshape(packed["shape"])


def _walked(value: object) -> bool:
    """An object whose attributes are state: of a class of `STATE_PACKAGE`, not a configuration."""
    return (
        type(value).__module__.startswith(STATE_PACKAGE)
        and hasattr(value, "__dict__")
        and not isinstance(value, BaseModel)
    )


def _name(cls: type) -> str:
    return f"{cls.__module__}:{cls.__qualname__}"


def _class(name: str) -> type:
    module, _, qualname = name.partition(":")
    if not module.startswith(STATE_PACKAGE):
        raise ValueError(f"environment state names a class outside {STATE_PACKAGE}: {name}")
    return getattr(importlib.import_module(module), qualname)


@functools.cache
def _field_names() -> tuple[str, ...]:
    """The names of the array fields of an `mujoco.MjModel`."""
    model = mujoco.MjModel.from_xml_string("<mujoco/>")
    return tuple(
        name
        for name in dir(model)
        if not name.startswith("_") and isinstance(getattr(model, name), np.ndarray)
    )


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    """Equal to the bit (NaN as NaN, -0.0 not as 0.0)."""
    return a.shape == b.shape and a.dtype == b.dtype and a.tobytes() == b.tobytes()


def _restore(live: object, saved: object, base: mujoco.MjModel) -> object:
    """The value that `saved` restores where `live` is now: `live` itself, updated in place
    where it can be, else a new value."""
    if isinstance(saved, torch.Tensor) or (isinstance(saved, dict) and saved[KIND] == "chunks"):
        return _restore_array(live, _unpacked(saved))
    if isinstance(saved, list):
        if isinstance(live, list) and len(live) == len(saved):
            for i, item in enumerate(saved):
                live[i] = _restore(live[i], item, base)
            return live
        return [_restore(None, item, base) for item in saved]
    if not isinstance(saved, dict):  # None, a number or a string
        return live if type(live) is type(saved) and live == saved else saved
    kind = saved[KIND]
    if kind == "seen":
        return live
    if kind == "scalar":
        value = saved["value"].numpy()[()]
        return live if type(live) is type(value) and live == value else value
    if kind == "rng":  # into the generator of the same place (as for the next two)
        cast(np.random.Generator, live).bit_generator.state = saved["state"]
        return live
    if kind == "batch":
        cast(mujoco.batch.Batch, live).state[...] = saved["state"].numpy()
        return live
    if kind == "model":
        _restore_model(cast(mujoco.MjModel, live), saved["fields"], base)
        return live
    if kind == "dict":
        items = saved["items"]
        if isinstance(live, dict):
            for key, item in items.items():
                live[key] = _restore(live.get(key), item, base)
            return live
        return {key: _restore(None, item, base) for key, item in items.items()}
    if kind in ("tuple", "named"):  # immutable: made again where an item changed
        cls = tuple if kind == "tuple" else _class(saved["class"])
        same = isinstance(live, tuple) and type(live) is cls and len(live) == len(saved["items"])
        olds = list(cast(tuple, live)) if same else [None] * len(saved["items"])
        items = [_restore(old, item, base) for old, item in zip(olds, saved["items"], strict=True)]
        if same and all(new is old for new, old in zip(items, olds, strict=True)):
            return live
        return cls(items) if kind == "tuple" else cls(*items)
    if kind == "object":
        for key, item in saved["attrs"].items():  # one set in an episode may not be there yet
            now = getattr(live, key, None)
            new = _restore(now, item, base)
            if new is not now or not hasattr(live, key):
                setattr(live, key, new)
        return live
    raise ValueError(f"unknown node {kind!r} in an environment state")


def _restore_array(live: object, array: np.ndarray) -> np.ndarray:
    if isinstance(live, np.ndarray) and live.shape == array.shape and live.dtype == array.dtype:
        if live.flags.writeable:
            live[...] = array
            return live
        if live.base is not None:
            return live  # a view of what the simulations compute: recomputed by `restore`
    return array.copy()


def _restore_model(model: mujoco.MjModel, fields: dict[str, object], base: mujoco.MjModel) -> None:
    """Give a copy's model the base model's fields, but for the `fields` kept (a field kept as
    a view of another array is restored with it)."""
    for name in _field_names():
        value = getattr(model, name)
        node = fields.get(name)
        if isinstance(node, dict) and node[KIND] == "seen":
            continue
        source = getattr(base, name) if node is None else _unpacked(node)
        if not _same(value, source):
            value[...] = source
