"""Crash-safe files: atomic writes, checks of saved model zips before they are loaded, and of the
settings a loaded model's policy was rebuilt with (:func:`check_policy_settings`).

A file written with :func:`atomic_write` goes to a temporary file in the same folder, is flushed to
disk and then renamed over the target (``os.replace``), so a process killed at any moment leaves
either the old file or the new one, never half of one. The folder is flushed after the rename too,
so the new name survives a power cut or an operating system crash once the write has returned.
"""

from __future__ import annotations

import contextlib
import csv
import errno
import io
import json
import os
import re
import zipfile
import zlib
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import IO, Any

MODEL_MEMBERS = ("data", "policy.pth")
"""Members every SB3 model zip holds."""


TEMPORARY_SUFFIX = ".tmp"
"""End of the temporary files of :func:`atomic_write` (``.<name>.<pid>.tmp`` beside the target)."""


class ModelFileError(ValueError):
    """A saved file (model zip, replay buffer, training state) that sb3_hgrn will not load; the message
    names the file and says why."""


class DamagedModelFileError(ModelFileError):
    """A saved file that cannot be loaded: cut short, not a zip, or with unreadable contents."""


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike, mode: str = "w") -> Iterator[IO[Any]]:
    """Open a temporary file beside ``path`` for writing; on success it replaces ``path``.

    :param mode: ``"w"`` (text, UTF-8, written as given: no newline translation, as the ``csv``
        module expects) or ``"wb"`` (binary).
    """
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}{TEMPORARY_SUFFIX}")
    text = {} if "b" in mode else {"encoding": "utf-8", "newline": ""}
    try:
        with open(tmp, mode, **text) as file:
            yield file
            file.flush()
            os.fsync(file.fileno())
        os.replace(tmp, path)
        sync_folder(path.parent)
    finally:
        tmp.unlink(missing_ok=True)


def sync_folder(folder: str | os.PathLike) -> None:
    """Flush ``folder``'s entries (names created, renamed or removed in it) to disk.

    Where folders cannot be opened for this (Windows), nothing is done.
    """
    try:
        descriptor = os.open(folder, os.O_RDONLY)
    except (PermissionError, IsADirectoryError):  # Windows cannot open a folder as a file
        return
    try:
        os.fsync(descriptor)
    except OSError as error:  # file systems that cannot flush a folder say so with EINVAL
        if error.errno not in (errno.EINVAL, errno.ENOTSUP):
            raise
    finally:
        os.close(descriptor)


def remove_temporary_files(folder: str | os.PathLike) -> int:
    """Remove the temporary files that :func:`atomic_write` left under ``folder`` when its process was
    killed mid-write; call it only while no other process writes there (e.g. holding the run lock).

    :return: the number of files removed.
    """
    pattern = re.compile(rf"\..+\.\d+{re.escape(TEMPORARY_SUFFIX)}")  # .<name>.<pid>.tmp only
    leftovers = [path for path in Path(folder).rglob(f".*{TEMPORARY_SUFFIX}") if pattern.fullmatch(path.name)]
    for path in leftovers:
        path.unlink(missing_ok=True)
    return len(leftovers)


def write_text_atomically(path: str | os.PathLike, text: str) -> None:
    """Write ``text`` to ``path`` with :func:`atomic_write`."""
    with atomic_write(path) as file:
        file.write(text)


def write_csv_atomically(path: str | os.PathLike, rows: Sequence[dict[str, Any]]) -> None:
    """Write ``rows`` as a CSV file with :func:`atomic_write`: one column per key (in order of first
    appearance), ``None`` as an empty cell."""
    fields = list(dict.fromkeys(key for row in rows for key in row))
    with atomic_write(path) as file:
        writer = csv.DictWriter(file, fieldnames=fields)
        writer.writeheader()
        for row in rows:
            writer.writerow({key: "" if value is None else value for key, value in row.items()})


def save_atomically(save: Callable[[IO[bytes]], Any], path: str | os.PathLike) -> None:
    """``save(file)`` into a binary file opened with :func:`atomic_write` for ``path``."""
    with atomic_write(path, "wb") as file:
        save(file)


def save_model_atomically(model: Any, path: str | os.PathLike) -> None:
    """``model.save(path)`` (an SB3 model) through :func:`atomic_write`."""
    save_atomically(model.save, path)


def model_file_path(path: str | os.PathLike, suffix: str = ".zip") -> Path:
    """The file SB3's ``load`` reads for ``path``: ``path`` itself, else ``<path><suffix>`` (SB3 adds
    ``.zip`` to model paths, ``.pkl`` to replay-buffer paths)."""
    path = Path(path)
    return path if path.exists() else Path(f"{path}{suffix}")


def existing_saved_file(path: str | os.PathLike, what: str = "model", suffix: str = ".zip") -> Path:
    """:func:`model_file_path` of ``path``, or a ``FileNotFoundError`` naming ``path`` as given
    (``No saved <what> at ...``) when neither it nor ``<path><suffix>`` is a file."""
    file = model_file_path(path, suffix)
    if not file.is_file():
        tried = "" if str(path).endswith(suffix) else f" (nor {os.fspath(path)}{suffix})"
        raise FileNotFoundError(f"No saved {what} at {os.fspath(path)}{tried}.")
    return file


def _check_torch_member(archive: zipfile.ZipFile, name: str, path: Path) -> None:
    """Raise :class:`DamagedModelFileError` naming ``path`` and the member unless the member ``name``
    (a ``torch.save`` file, itself a zip archive) is whole."""
    try:
        with zipfile.ZipFile(io.BytesIO(archive.read(name))) as inner:
            broken = inner.testzip()
    except (zipfile.BadZipFile, zlib.error, EOFError) as error:
        raise DamagedModelFileError(
            f"damaged model file {path}: member {name!r} is not a whole torch file ({error})"
        ) from error
    if broken is not None:
        raise DamagedModelFileError(
            f"damaged model file {path}: member {name!r}: {broken!r} fails its checksum"
        )


def check_model_file(path: str | os.PathLike) -> Path:
    """Raise :class:`DamagedModelFileError` naming ``path`` unless it is a whole SB3 model zip (a
    readable zip with intact members, among them ``data`` as JSON and ``policy.pth``, and every
    ``.pth`` member a whole torch file).

    :return: the file (``path``, or ``<path>.zip`` as SB3 reads it).
    :raises FileNotFoundError: naming ``path`` when there is no file at it (nor at ``<path>.zip``).
    """
    path = existing_saved_file(path)
    try:
        with zipfile.ZipFile(path) as archive:
            broken = archive.testzip()
            missing = [name for name in MODEL_MEMBERS if name not in archive.namelist()]
            if broken is None and not missing:
                json.loads(archive.read("data"))
                for name in archive.namelist():
                    if name.endswith(".pth"):
                        _check_torch_member(archive, name, path)
    except DamagedModelFileError:
        raise
    except (zipfile.BadZipFile, zlib.error, OSError, ValueError, EOFError) as error:
        raise DamagedModelFileError(f"damaged model file {path}: {error}") from error
    if broken is not None:
        raise DamagedModelFileError(f"damaged model file {path}: member {broken!r} fails its checksum")
    if missing:
        raise DamagedModelFileError(f"damaged model file {path}: no {', '.join(missing)} in the zip")
    return path


ZipSource = str | os.PathLike | io.BytesIO
"""A model zip: its path (the ``.zip`` may be left out, as in SB3) or its bytes in memory."""


def open_model_zip(source: ZipSource) -> zipfile.ZipFile:
    """The model zip ``source`` opened for reading."""
    return zipfile.ZipFile(source if isinstance(source, io.BytesIO) else model_file_path(source))


def saved_data(source: ZipSource) -> dict[str, Any]:
    """The ``data`` JSON of a whole SB3 model zip, as written (pickled entries left as they are)."""
    with open_model_zip(source) as archive:
        return json.loads(archive.read("data"))


def saved_policy_class(source: ZipSource) -> tuple[str, str]:
    """Module and name of the policy class recorded in a whole SB3 model zip (``""`` for what is not
    recorded; SB3 keeps the name only inside the recorded methods, ``<function NAME.method ...>``)."""
    policy_class = saved_data(source).get("policy_class")
    if not isinstance(policy_class, dict):
        return "", ""
    methods = (re.match(r"<function (\w+)\.", str(value)) for value in policy_class.values())
    names = [match.group(1) for match in methods if match]
    return str(policy_class.get("__module__", "")), names[0] if names else ""


def saved_policy_module(source: ZipSource) -> str:
    """The module of the policy class recorded in a whole SB3 model zip (``""`` if none is)."""
    return saved_policy_class(source)[0]


def describe_saved_model(source: ZipSource) -> str:
    """What saved a model zip, in words, from its policy class: ``"stable_baselines3's DQN (policy
    DQNPolicy)"`` for ``stable_baselines3.dqn.policies``; the class's module for other libraries."""
    module, name = saved_policy_class(source)
    package, _, rest = module.partition(".")
    algorithm = rest.split(".")[0]
    policy = f" (policy {name})" if name else ""
    if not module:
        return "an unknown library (no policy class recorded)"
    if algorithm and algorithm != "common":
        return f"{package}'s {algorithm.upper()}{policy}"
    return f"{package}{policy}, policy module {module}"


def check_policy_settings(model: Any, names: Sequence[str]) -> None:
    """Raise a ``ValueError`` when a just loaded ``model`` holds one of the algorithm arguments
    ``names`` with another value than its policy, which was rebuilt from the saved settings: such an
    argument given to ``load`` would rename the policy while the saved one kept acting."""
    for name in names:
        given, built = getattr(model, name), getattr(model.policy, name)
        if given != built:
            raise ValueError(
                f"This model's policy was built with {name}={built!r}; load cannot change it to "
                f"{given!r}. Build a new model with {name}={given!r} instead."
            )
