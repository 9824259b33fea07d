"""One process per run folder: an OS file lock (the ``filelock`` package) with the holder's pid beside it.

The lock is ``<run>/.lock``, held with ``flock`` for as long as a process trains in (or writes the
evaluation of) the run; the holder writes its pid into ``<run>/.lock.pid`` and removes it when it
lets go. The operating system releases the lock of a process that dies, even by ``kill -9``, so the
next process takes it over at once; the pid file the dead process left behind makes that visible
with a warning.
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path
from types import TracebackType

import filelock

from sb3_hgrn.common.files import write_text_atomically
from sb3_hgrn.experiments.config import ConfigError

LOCK_FILE = ".lock"
PID_FILE = ".lock.pid"


def _holder_pid(folder: Path) -> int | None:
    """The pid recorded in ``folder``'s pid file, if any."""
    try:
        return int((folder / PID_FILE).read_text(encoding="utf-8").strip())
    except (OSError, ValueError):
        return None


def _holder(folder: Path) -> str:
    """``process <pid>`` of the lock's holder (``another process`` before it has written its pid)."""
    pid = _holder_pid(folder)
    return "another process" if pid is None else f"process {pid}"


class RunFolderLocked(ConfigError):
    """Another living process holds the run folder's lock."""


class RunLock:
    """Exclusive lock of a run folder, as a context manager (the folder is created if needed).

    Entering raises :class:`RunFolderLocked`, naming the holder's pid, when another process holds it,
    and warns when it takes over the lock of a process that died without letting go.

    :param folder: the run folder.
    """

    def __init__(self, folder: str | os.PathLike):
        self.folder = Path(folder)
        self._lock = filelock.FileLock(str(self.folder / LOCK_FILE))

    def __enter__(self) -> RunLock:
        self.folder.mkdir(parents=True, exist_ok=True)
        try:
            self._lock.acquire(timeout=0)
        except filelock.Timeout:
            raise RunFolderLocked(
                f"{self.folder} is in use by {_holder(self.folder)} (it holds {self.folder / LOCK_FILE}): "
                "wait for it to finish, or stop it, before starting another run there."
            ) from None
        previous = _holder_pid(self.folder)
        if previous is not None and previous != os.getpid():
            warnings.warn(
                f"Taking over the lock of {self.folder} from process {previous}, which ended without "
                "releasing it.",
                stacklevel=2,
            )
        write_text_atomically(self.folder / PID_FILE, f"{os.getpid()}\n")
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        (self.folder / PID_FILE).unlink(missing_ok=True)
        self._lock.release()


def lock_holder(folder: str | os.PathLike) -> str | None:
    """``process <pid>`` if a living process holds ``folder``'s lock, else ``None`` (a missing folder
    is not locked)."""
    folder = Path(folder)
    if not folder.is_dir():
        return None
    lock = filelock.FileLock(str(folder / LOCK_FILE))
    try:
        lock.acquire(timeout=0)
    except filelock.Timeout:
        return _holder(folder)
    lock.release()
    return None
