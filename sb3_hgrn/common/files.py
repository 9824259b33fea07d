"""Crash-safe files: atomic writes, and checks of saved model zips before they are loaded.

A file written with :func:`atomic_write` goes to a temporary file in the same folder, is flushed to
disk and then renamed over the target (``os.replace``), so a process killed at any moment leaves
either the old file or the new one, never half of one. The folder is flushed after the rename too,
so the new name survives a power cut or an operating system crash once the write has returned.
"""

from __future__ import annotations

import contextlib
import csv
import errno
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


class DamagedModelFileError(ValueError):
    """A model zip that cannot be loaded: cut short, not a zip, or with unreadable contents."""


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


def model_file_path(path: str | os.PathLike) -> Path:
    """The file SB3's ``load`` reads for ``path``: ``path`` itself, else ``<path>.zip``."""
    path = Path(path)
    return path if path.exists() else Path(f"{path}.zip")


def check_model_file(path: str | os.PathLike) -> None:
    """Raise :class:`DamagedModelFileError` naming ``path`` unless it is a whole SB3 model zip (a
    readable zip with intact members, among them ``data`` as JSON and ``policy.pth``).

    A missing file is left to the loader (its own ``FileNotFoundError``).
    """
    path = model_file_path(path)
    if not path.is_file():
        return
    try:
        with zipfile.ZipFile(path) as archive:
            broken = archive.testzip()
            missing = [name for name in MODEL_MEMBERS if name not in archive.namelist()]
            if broken is None and not missing:
                json.loads(archive.read("data"))
    except (zipfile.BadZipFile, zlib.error, OSError, ValueError, EOFError) as error:
        raise DamagedModelFileError(f"damaged model file {path}: {error}") from error
    if broken is not None:
        raise DamagedModelFileError(f"damaged model file {path}: member {broken!r} fails its checksum")
    if missing:
        raise DamagedModelFileError(f"damaged model file {path}: no {', '.join(missing)} in the zip")


def saved_policy_module(path: str | os.PathLike) -> str:
    """The module of the policy class recorded in a whole SB3 model zip (``""`` if none is)."""
    with zipfile.ZipFile(model_file_path(path)) as archive:
        policy_class = json.loads(archive.read("data")).get("policy_class")
    return policy_class.get("__module__", "") if isinstance(policy_class, dict) else ""
