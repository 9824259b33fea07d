"""Loading saved files without running code from them.

A pickle can call any function while it is loaded, so a model zip, replay buffer or training state from
an untrusted source could run code. sb3_hgrn reads them without that power:

- a model zip's settings that SB3 pickles (spaces, schedules, train frequency, the policy class, the
  last observation) are also written as plain data, the member :data:`RECORD_MEMBER` (JSON, see
  :func:`to_plain`), and rebuilt from it; weights are read with ``torch.load(weights_only=True)``;
- anything else pickled (the entries of zips saved before that record existed, replay buffers,
  training states) is read by :func:`restricted_loads`, an unpickler that builds only the types of
  :data:`ALLOWED_GLOBALS` (numpy arrays, gymnasium spaces, SB3 schedules, ...) and the classes its
  caller names; any other reference raises :class:`UntrustedPickleError`.

Passing ``trust_pickle=True`` where a file is loaded unpickles it in full, as SB3 does.
"""

from __future__ import annotations

import base64
import collections
import importlib
import io
import json
import os
import pickle
import zipfile
from collections.abc import Callable, Iterable
from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.save_util import open_path
from stable_baselines3.common.type_aliases import TrainFreq, TrainFrequencyUnit
from stable_baselines3.common.utils import ConstantSchedule, FloatSchedule, LinearSchedule

from sb3_hgrn.common.files import (
    DamagedModelFileError,
    ModelFileError,
    ZipSource,
    existing_saved_file,
    open_model_zip,
)

RECORD_MEMBER = "sb3_hgrn.json"
"""Member of a model zip with the plain-data form of the entries that SB3 pickles into ``data``."""

RECORD_FORMAT = 1
TRUST_HINT = "Pass trust_pickle=True (--trust-pickle) only if you trust the file: unpickling it can run code"

_PLAIN_CLASSES: tuple[type, ...] = (
    spaces.Box,
    spaces.Discrete,
    spaces.MultiDiscrete,
    spaces.MultiBinary,
    spaces.Dict,
    spaces.Tuple,
    ConstantSchedule,
    LinearSchedule,
    FloatSchedule,
    TrainFreq,
    TrainFrequencyUnit,
    collections.deque,
    collections.OrderedDict,
    th.device,
)

ALLOWED_GLOBALS: dict[tuple[str, str], Any] = {
    **{(cls.__module__, cls.__name__): cls for cls in _PLAIN_CLASSES},
    **{
        (module, name): getattr(importlib.import_module(module), name)
        for module, names in {
            "numpy": ("dtype", "ndarray"),
            "numpy._core.multiarray": ("_reconstruct", "scalar"),
            "numpy._core.numeric": ("_frombuffer",),
            "numpy.random._pickle": ("__generator_ctor", "__bit_generator_ctor", "__randomstate_ctor"),
            "numpy.random.bit_generator": ("__pyx_unpickle_SeedSequence", "SeedSequence"),
            "numpy.random._generator": ("Generator",),
            "numpy.random.mtrand": ("RandomState",),
            "numpy.random._pcg64": ("PCG64", "PCG64DXSM"),
            "numpy.random._philox": ("Philox",),
            "numpy.random._sfc64": ("SFC64",),
            "numpy.random._mt19937": ("MT19937",),
            "numpy.dtypes": tuple(name for name in dir(np.dtypes) if name.endswith("DType")),
            "builtins": ("set", "frozenset", "bytearray", "complex", "slice"),
        }.items()
        for name in names
    },
}
"""What :func:`restricted_loads` may build: ``(module, name)`` -> object. Besides numpy arrays and
generators, gymnasium spaces and SB3's schedules, none of them does more than hold data."""
ALLOWED_GLOBALS.update(  # numpy < 2 pickles its arrays from numpy.core
    {
        (module.replace("numpy._core", "numpy.core"), name): value
        for (module, name), value in ALLOWED_GLOBALS.items()
        if module.startswith("numpy._core")
    }
)


class UntrustedPickleError(ModelFileError):
    """A file that can only be loaded by unpickling something that could run code."""


class _RestrictedUnpickler(pickle._Unpickler):
    """Unpickler that resolves only :data:`ALLOWED_GLOBALS` and the given classes, and sets state
    only on objects, never on a class (which would change it for the whole process).

    It is pickle's pure-Python unpickler, whose opcodes can be overridden (the C one's cannot).
    """

    def __init__(self, file: io.BytesIO, source: str, classes: Iterable[type]):
        super().__init__(file)
        self.source = source
        self.classes = {(cls.__module__, cls.__qualname__): cls for cls in classes}

    def find_class(self, module: str, name: str) -> Any:
        found = ALLOWED_GLOBALS.get((module, name), self.classes.get((module, name)))
        if found is None:
            raise UntrustedPickleError(
                f"{self.source} refers to {module}.{name}, which sb3_hgrn does not build from a file."
            )
        return found

    def load_build(self) -> None:
        target = self.stack[-2]
        if isinstance(target, type):
            raise UntrustedPickleError(f"{self.source} sets attributes of the class {target.__qualname__}.")
        super().load_build()

    dispatch = {**pickle._Unpickler.dispatch, pickle.BUILD[0]: load_build}


def restricted_loads(data: bytes, source: str, classes: Iterable[type] = ()) -> Any:
    """Unpickle ``data`` building only :data:`ALLOWED_GLOBALS` and ``classes``.

    :param source: what ``data`` is, for error messages (e.g. ``"the replay buffer runs/x.pkl"``).
    :raises UntrustedPickleError: naming ``source`` and the first reference it may not build.
    :raises pickle.UnpicklingError, EOFError: when ``data`` is not a whole pickle.
    """
    return _RestrictedUnpickler(io.BytesIO(data), source, classes).load()


def load_pickle(data: bytes, source: str, trust_pickle: bool, classes: Iterable[type] = ()) -> Any:
    """``pickle.loads(data)`` with ``trust_pickle``, else :func:`restricted_loads`, whose refusal then
    says how to load ``source`` in full."""
    if trust_pickle:
        return pickle.loads(data)
    try:
        return restricted_loads(data, source, classes)
    except UntrustedPickleError as error:
        raise UntrustedPickleError(f"{error} {TRUST_HINT}.") from error


# --- plain data: JSON with tagged objects ---------------------------------------------------------
TAG = "__plain__"
Decode = Callable[[Any], Any]


class NotPlainError(TypeError):
    """A value that :func:`to_plain` has no plain form for (e.g. a function)."""


def _array_to_plain(array: np.ndarray) -> dict[str, Any]:
    if array.dtype.hasobject:
        raise NotPlainError("an array of Python objects")
    array = np.ascontiguousarray(array)
    return {
        TAG: "ndarray",
        "dtype": array.dtype.str,
        "shape": list(array.shape),
        "data": base64.b64encode(array.tobytes()).decode(),
    }


def _array_from_plain(data: dict[str, Any]) -> np.ndarray:
    dtype = np.dtype(data["dtype"])
    if dtype.hasobject:
        raise ValueError("an array of Python objects")
    return np.frombuffer(base64.b64decode(data["data"]), dtype=dtype).reshape(data["shape"]).copy()


def _class_to_plain(cls: type) -> dict[str, Any]:
    return {TAG: "class", "module": cls.__module__, "name": cls.__qualname__}


def _space_to_plain(space: spaces.Space) -> dict[str, Any]:
    if isinstance(space, spaces.Box):
        fields = {"low": space.low, "high": space.high, "shape": list(space.shape), "dtype": space.dtype.str}
    elif isinstance(space, spaces.Discrete):
        fields = {"n": int(space.n), "start": int(space.start)}
    elif isinstance(space, spaces.MultiDiscrete):
        fields = {"nvec": space.nvec, "start": space.start, "dtype": space.dtype.str}
    elif isinstance(space, spaces.MultiBinary):
        fields = {"n": space.n}
    elif isinstance(space, spaces.Dict):
        fields = {"spaces": [[key, value] for key, value in space.spaces.items()]}
    elif isinstance(space, spaces.Tuple):
        fields = {"spaces": list(space.spaces)}
    else:
        raise NotPlainError(f"the space {type(space).__name__}")
    return {TAG: "space", "type": type(space).__name__, **{k: to_plain(v) for k, v in fields.items()}}


def _space_from_plain(data: dict[str, Any], decode: Decode) -> spaces.Space:
    kind = data["type"]
    if kind == "Box":
        shape = tuple(data["shape"])  # bounds of one value per entry (a space of shape () may hold (1,))
        low, high = (np.reshape(decode(data[key]), shape) for key in ("low", "high"))
        return spaces.Box(low, high, shape, dtype=np.dtype(data["dtype"]))
    if kind == "Discrete":
        return spaces.Discrete(int(data["n"]), start=int(data["start"]))
    if kind == "MultiDiscrete":
        nvec, start = decode(data["nvec"]), decode(data["start"])
        return spaces.MultiDiscrete(nvec, dtype=np.dtype(data["dtype"]), start=start)
    if kind == "MultiBinary":
        return spaces.MultiBinary(decode(data["n"]))
    if kind == "Dict":
        return spaces.Dict([(key, decode(value)) for key, value in data["spaces"]])
    if kind == "Tuple":
        return spaces.Tuple([decode(value) for value in data["spaces"]])
    raise ValueError(f"unknown space type {kind!r}")


def to_plain(value: Any) -> Any:
    """A JSON-serialisable form of ``value`` that :func:`from_plain` turns back into an equal value.

    Handles JSON's own types, tuples, numpy arrays and scalars, deques, gymnasium spaces (Box,
    Discrete, MultiDiscrete, MultiBinary, Dict, Tuple), SB3's constant, linear and float schedules,
    its ``TrainFreq``, and references to classes (kept by module and name).

    :raises NotPlainError: for anything else (a function, an object of another class).
    """
    if value is None or isinstance(value, bool | int | float | str):
        return value
    if isinstance(value, np.ndarray):
        return _array_to_plain(value)
    if isinstance(value, np.generic):
        return {TAG: "scalar", "array": _array_to_plain(np.asarray(value))}
    if isinstance(value, TrainFreq):
        return {TAG: "train_freq", "frequency": int(value.frequency), "unit": value.unit.value}
    if isinstance(value, tuple):
        return {TAG: "tuple", "items": [to_plain(item) for item in value]}
    if isinstance(value, list):
        return [to_plain(item) for item in value]
    if isinstance(value, collections.deque):
        return {TAG: "deque", "maxlen": value.maxlen, "items": [to_plain(item) for item in value]}
    if isinstance(value, dict):
        if not all(isinstance(key, str) for key in value):
            raise NotPlainError("a dict with keys that are not strings")
        return {TAG: "dict", "items": {key: to_plain(item) for key, item in value.items()}}
    if isinstance(value, spaces.Space):
        return _space_to_plain(value)
    if isinstance(value, ConstantSchedule):
        return {TAG: "constant_schedule", "value": float(value.val)}
    if isinstance(value, LinearSchedule):
        fields = {"start": value.start, "end": value.end, "end_fraction": value.end_fraction}
        return {TAG: "linear_schedule", **{key: float(item) for key, item in fields.items()}}
    if isinstance(value, FloatSchedule):
        return {TAG: "float_schedule", "schedule": to_plain(value.value_schedule)}
    if isinstance(value, type):
        return _class_to_plain(value)
    raise NotPlainError(f"a {type(value).__module__}.{type(value).__qualname__}")


_DECODERS: dict[str, Callable[[dict[str, Any], Decode], Any]] = {
    "ndarray": lambda data, decode: _array_from_plain(data),
    "scalar": lambda data, decode: _array_from_plain(data["array"])[()],
    "train_freq": lambda data, decode: TrainFreq(int(data["frequency"]), TrainFrequencyUnit(data["unit"])),
    "tuple": lambda data, decode: tuple(decode(item) for item in data["items"]),
    "deque": lambda data, decode: collections.deque(map(decode, data["items"]), data["maxlen"]),
    "dict": lambda data, decode: {key: decode(item) for key, item in data["items"].items()},
    "space": lambda data, decode: _space_from_plain(data, decode),
    "constant_schedule": lambda data, decode: ConstantSchedule(float(data["value"])),
    "linear_schedule": lambda data, decode: LinearSchedule(
        float(data["start"]), float(data["end"]), float(data["end_fraction"])
    ),
    "float_schedule": lambda data, decode: FloatSchedule(decode(data["schedule"])),
}


def from_plain(data: Any, classes: Iterable[type] = ()) -> Any:
    """The value whose :func:`to_plain` form is ``data``; it refers to no class but ``classes``.

    :raises UntrustedPickleError: for a reference to a class outside ``classes``.
    :raises ValueError, KeyError, TypeError: for data that is no such form.
    """
    allowed = {(cls.__module__, cls.__qualname__): cls for cls in classes}

    def decode(item: Any) -> Any:
        if isinstance(item, list):
            return [decode(element) for element in item]
        if not isinstance(item, dict):
            return item
        if item[TAG] != "class":
            return _DECODERS[item[TAG]](item, decode)
        found = allowed.get((item["module"], item["name"]))
        if found is None:
            raise UntrustedPickleError(
                f"the record refers to {item['module']}.{item['name']}, which sb3_hgrn does not build "
                "from a file."
            )
        return found

    return decode(data)


def add_plain_record(archive: io.BytesIO, values: dict[str, Any]) -> None:
    """Append :data:`RECORD_MEMBER` to the SB3 model zip in ``archive``: the plain form of
    ``values[key]`` (the saved object's attributes) for every entry SB3 pickled into ``data``; those
    without one (a function, an object of another class) are left out."""
    with zipfile.ZipFile(archive) as zipped:
        data = json.loads(zipped.read("data"))
    entries = {}
    for key in _pickled_keys(data):
        try:
            entries[key] = to_plain(values[key])
        except NotPlainError:
            continue
    with zipfile.ZipFile(archive, "a", compression=zipfile.ZIP_DEFLATED) as zipped:
        zipped.writestr(RECORD_MEMBER, json.dumps({"format": RECORD_FORMAT, "entries": entries}))


def _pickled_keys(data: dict[str, Any]) -> list[str]:
    """The entries of a model zip's ``data`` JSON that SB3 pickled."""
    return [key for key, item in data.items() if isinstance(item, dict) and ":serialized:" in item]


def saved_entries(source: ZipSource, name: str, classes: Iterable[type], skip: Iterable[str] = ()) -> dict:
    """Every entry SB3 pickled into the ``data`` of a model zip, rebuilt without running code from it:
    from :data:`RECORD_MEMBER`, else (zips saved without it) by :func:`restricted_loads`; pass them to
    SB3's ``load`` as ``custom_objects``, so that it unpickles nothing.

    :param name: the file's name for error messages.
    :param classes: the classes the entries may refer to (policy classes, optimisers).
    :param skip: entries not to rebuild (the caller gives them).
    :raises UntrustedPickleError: naming the file and every entry that cannot be rebuilt.
    """
    classes = tuple(classes)
    with open_model_zip(source) as archive:
        data = json.loads(archive.read("data"))
        has_record = RECORD_MEMBER in archive.namelist()
        record = json.loads(archive.read(RECORD_MEMBER))["entries"] if has_record else {}
    entries, refused = {}, {}
    for key in [key for key in _pickled_keys(data) if key not in set(skip)]:
        try:
            entries[key] = _saved_entry(key, data[key], record, classes)
        except UntrustedPickleError as error:
            refused[key] = error
        except (pickle.UnpicklingError, EOFError, ValueError, KeyError, TypeError) as error:
            raise DamagedModelFileError(f"damaged model file {name}: entry {key!r}: {error}") from error
    if refused:
        reasons = " ".join(str(error) for error in refused.values())
        raise UntrustedPickleError(
            f"{name}: the entries {', '.join(map(repr, refused))} cannot be loaded without running code "
            f"from the file: {reasons} {TRUST_HINT}."
        )
    return entries


def _saved_entry(
    key: str, serialized: dict[str, Any], record: dict[str, Any], classes: tuple[type, ...]
) -> Any:
    """The entry ``key`` of a model zip's ``data``: from its plain form in ``record`` if there is one,
    else from its pickle ``serialized`` by :func:`restricted_loads`."""
    if key in record:
        return from_plain(record[key], classes)
    return restricted_loads(base64.b64decode(serialized[":serialized:"]), f"the entry {key!r}", classes)


def read_saved_pickle(
    path: str | os.PathLike | io.BufferedIOBase,
    what: str,
    suffix: str = ".pkl",
    trust_pickle: bool = False,
    classes: Iterable[type] = (),
) -> Any:
    """The object pickled in the file ``path`` (``<path><suffix>`` if ``path`` is not a file, as SB3
    reads it), by :func:`load_pickle`.

    :param what: what the file holds, for error messages (``"replay buffer"``).
    :raises FileNotFoundError: naming ``path`` as given when there is no such file.
    :raises DamagedModelFileError: for a file cut short or not a pickle, naming it.
    :raises UntrustedPickleError: for a file that needs more than ``classes`` to be unpickled.
    """
    if isinstance(path, str | os.PathLike):
        file = existing_saved_file(path, what, suffix)
        name, content = os.fspath(file), file.read_bytes()
    else:
        name, content = f"the {what} file", path.read()
    try:
        return load_pickle(content, f"the {what} {name}", trust_pickle, classes)
    except UntrustedPickleError:
        raise
    except (pickle.UnpicklingError, EOFError, ValueError, KeyError, IndexError) as error:
        raise DamagedModelFileError(f"damaged {what} file {name}: {error!r}") from error


def write_zip(path: str | os.PathLike | io.IOBase, content: bytes) -> None:
    """Write ``content`` to ``path`` as SB3's ``save`` does (``.zip`` added to a path without a suffix,
    missing folders made) or into an open binary file."""
    if not isinstance(path, str | os.PathLike):
        path.write(content)
        return
    with open_path(path, "w", verbose=0, suffix="zip") as file:
        file.write(content)
