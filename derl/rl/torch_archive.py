"""The bytes of `torch.save` read without torch, its tensors as numpy arrays: for a process that
checks checkpoints but never runs a policy (the coordinator, which torch's import would cost
about 1.3 s of CPU and 230 MB of memory at its first report).

A `torch.save` file is a zip archive: `<name>/data.pkl` pickles the object, each tensor a call of
`torch._utils._rebuild_tensor_v2` on a storage that the pickle names by a persistent id and whose
bytes are the member `<name>/data/<key>`. The unpickler here accepts what torch's weights-only
reader accepts for a checkpoint of plain data (dicts, lists, tuples, numbers, strings, an empty
`OrderedDict` of hooks, tensors of CPU storages) and refuses every other global with
`pickle.UnpicklingError`: no pickled code runs. A tensor's view must lie inside its storage, and
what was read must be such plain data (numbers in every array: a pickle's BUILD could have made
one an array of objects).
"""

from __future__ import annotations

import collections
import io
import pickle
import zipfile
from dataclasses import dataclass
from typing import Any

import numpy as np

STORAGES = {
    "DoubleStorage": np.float64,
    "FloatStorage": np.float32,
    "HalfStorage": np.float16,
    "LongStorage": np.int64,
    "IntStorage": np.int32,
    "ShortStorage": np.int16,
    "CharStorage": np.int8,
    "ByteStorage": np.uint8,
    "BoolStorage": np.bool_,
}
"""torch's typed storage classes (as a pickle names them) -> the element type of their bytes."""


def load(data: bytes) -> Any:
    """The object `torch.save` wrote into `data`, tensors as (writable, C-ordered) numpy arrays;
    `ValueError` (or `zipfile.BadZipFile`, `pickle.UnpicklingError`) for bytes that are not one."""
    with zipfile.ZipFile(io.BytesIO(data)) as archive:
        pickles = [name for name in archive.namelist() if name.endswith("/data.pkl")]
        if len(pickles) != 1:
            raise ValueError("not a torch.save archive (no single data.pkl)")
        root = pickles[0].removesuffix("data.pkl")
        if archive.read(f"{root}byteorder") != b"little":
            raise ValueError("a big-endian torch.save archive")
        loaded = _Unpickler(archive, root).load()
    _check_plain(loaded)
    return loaded


PLAIN = (str, int, float, bool, type(None))
NUMBERS = "biuf"
"""The kinds of numpy dtype an array read may have: booleans, integers, floats."""


def _check_plain(value: Any) -> None:
    """`ValueError` unless `value` is plain data: PLAIN values, arrays of NUMBERS, and lists,
    tuples and dicts (string keys) of plain data."""
    if isinstance(value, np.ndarray):
        if value.dtype.kind not in NUMBERS:
            raise ValueError(f"an array of {value.dtype}")
    elif isinstance(value, dict):
        for key, item in value.items():
            if not isinstance(key, str):
                raise ValueError(f"a key {type(key).__name__}")
            _check_plain(item)
    elif isinstance(value, list | tuple):
        for item in value:
            _check_plain(item)
    elif not isinstance(value, PLAIN):
        raise ValueError(f"a {type(value).__name__}")


@dataclass(frozen=True, slots=True)
class _StorageType:
    """A storage class a pickle names: neither callable nor changeable by the pickle."""

    dtype: np.dtype


class _Unpickler(pickle.Unpickler):
    def __init__(self, archive: zipfile.ZipFile, root: str) -> None:
        super().__init__(io.BytesIO(archive.read(f"{root}data.pkl")))
        self.archive, self.root = archive, root
        self.storages: dict[str, np.ndarray] = {}

    def find_class(self, module: str, name: str) -> Any:
        if (module, name) == ("torch._utils", "_rebuild_tensor_v2"):
            return _rebuild_tensor
        if (module, name) == ("collections", "OrderedDict"):
            return collections.OrderedDict
        if module == "torch" and name in STORAGES:
            return _StorageType(np.dtype(STORAGES[name]))
        raise pickle.UnpicklingError(f"{module}.{name} is not allowed in a checkpoint")

    def persistent_load(self, pid: Any) -> np.ndarray:
        """A storage: ("storage", its type, key, location, element count) -> its elements."""
        if not (isinstance(pid, tuple) and len(pid) == 5 and pid[0] == "storage"):
            raise pickle.UnpicklingError(f"unknown persistent id {pid!r:.80}")
        _, kind, key, location, count = pid
        if not isinstance(kind, _StorageType) or location != "cpu" or not isinstance(key, str):
            raise pickle.UnpicklingError(f"a storage of {kind!r:.40} on {location!r:.20}")
        dtype = kind.dtype
        if key not in self.storages:
            raw = self.archive.read(f"{self.root}data/{key}")
            if not isinstance(count, int) or len(raw) != count * dtype.itemsize:
                raise ValueError(f"storage {key} holds {len(raw)} bytes, not {count} elements")
            self.storages[key] = np.frombuffer(raw, dtype)
        return self.storages[key]


def _rebuild_tensor(storage: Any, offset: Any, size: Any, stride: Any, *_: Any) -> np.ndarray:
    """A copy of the (size, stride) view at `offset` of `storage`'s elements, checked to lie in
    it (torch's `_rebuild_tensor_v2`; requires_grad, hooks and metadata do not matter here)."""
    shape, steps = tuple(size), tuple(stride)
    numbers = (offset, *shape, *steps)
    if not isinstance(storage, np.ndarray) or not all(isinstance(n, int) for n in numbers):
        raise pickle.UnpicklingError("a tensor that is not a view of a storage")
    if len(shape) != len(steps) or min(numbers) < 0:
        raise ValueError(f"a tensor of size {shape} and stride {steps}")
    last = offset + sum((n - 1) * s for n, s in zip(shape, steps, strict=True))
    if 0 not in shape and last >= len(storage):
        raise ValueError(f"a tensor of size {shape} reaches past its storage ({len(storage)})")
    elements = storage[offset:] if 0 not in shape else storage[:0]
    strides = tuple(s * storage.itemsize for s in steps)
    view = np.lib.stride_tricks.as_strided(elements, shape, strides, writeable=False)
    return np.array(view, order="C")
