"""Where the sweeps' runs execute: local processes, or Ray tasks on one machine or a cluster.

A backend starts one ``python -m sb3_hgrn ARGS`` process per run, its output going to the run's
log file, and hands back a :class:`RunHandle` that the job loop
(:func:`sb3_hgrn.experiments.table1.run_jobs`) polls. Both backends run the very same command, so
finished runs are skipped, killed runs resume from their checkpoints and run folders are locked
alike (:mod:`sb3_hgrn.experiments.lock`).

- :class:`LocalBackend`: a child process of the sweep's own process.
- :class:`RayBackend`: a Ray remote task (with ``num_cpus`` / ``num_gpus`` and the ``memory`` its
  replay buffer takes) that starts the process on whichever node Ray places it; the run folders must
  then lie on a file system that every node mounts at the same path. Ray is imported only when this
  backend is built (``pip install 'sb3_hgrn[ray]'``).

A stopped run ends within a bounded time, however loaded the machine: the run's process leads a
process group of its own, which :func:`stop_process` ends with ``SIGTERM`` and, ``STOP_GRACE_S``
later, ``SIGKILL``; a cancelled Ray task that has not ended ``RAY_CANCEL_GRACE_S`` after its interrupt
has its worker killed (``ray.cancel(force=True)``). And the process dies with the process that
started it (:func:`die_with_parent`), so that no run goes on when its sweep or Ray worker is killed.
"""

from __future__ import annotations

import ctypes
import os
import signal
import subprocess
import sys
import threading
import time
from abc import ABC, abstractmethod
from pathlib import Path
from typing import Any

from sb3_hgrn.experiments.config import ConfigError

BACKENDS = ("local", "ray")
RAY_INSTALL_COMMAND = "pip install 'sb3_hgrn[ray]'"
PARENT_PID_VARIABLE = "SB3_HGRN_PARENT_PID"
"""Environment variable naming, to a run's process, the process whose death ends it."""
STOP_GRACE_S = 5.0
"""Seconds a stopped run's processes have between ``SIGTERM`` and ``SIGKILL``."""
RAY_CANCEL_GRACE_S = 10.0
"""Seconds a cancelled Ray task has to end before its worker is killed, and again after that."""
PR_SET_PDEATHSIG = 1
"""Linux ``prctl`` option: the signal a process gets when the thread that started it ends."""
PARENT_POLL_S = 1.0
"""Seconds between two looks at the parent's pid where ``prctl`` is not available."""


def python_command(args: list[str]) -> list[str]:
    """``[sys.executable, "-m", "sb3_hgrn", *args]``: the command line of ``sb3-hgrn ARGS`` with this
    machine's interpreter."""
    return [sys.executable, "-m", "sb3_hgrn", *args]


def child_env(threads: int | None) -> dict[str, str]:
    """Environment of a run's process: this package importable, OpenMP / MKL threads capped if asked,
    this process named as the one whose death ends it (:data:`PARENT_PID_VARIABLE`)."""
    env = dict(os.environ)
    package_parent = str(Path(__file__).resolve().parents[2])
    env["PYTHONPATH"] = os.pathsep.join(p for p in (package_parent, env.get("PYTHONPATH", "")) if p)
    env[PARENT_PID_VARIABLE] = str(os.getpid())
    if threads is not None:
        for name in ("OMP_NUM_THREADS", "MKL_NUM_THREADS"):
            env[name] = str(threads)
    return env


def start_logged(
    args: list[str], log_path: Path, threads: int | None, cwd: str | None = None
) -> tuple[subprocess.Popen, Any]:
    """Start ``sb3-hgrn ARGS`` in the directory ``cwd`` (default this process's) with stdout and
    stderr appended to ``log_path`` (a resumed run keeps the log of its killed attempt):
    ``(process, open log file)``. The process leads a new session (and process group), so that
    :func:`stop_process` reaches all it starts and a terminal's Ctrl-C reaches the sweep alone."""
    log_file = open(log_path, "a", encoding="utf-8")  # noqa: SIM115
    process = subprocess.Popen(
        python_command(args),
        stdout=log_file,
        stderr=subprocess.STDOUT,
        env=child_env(threads),
        cwd=cwd,
        start_new_session=True,
    )
    return process, log_file


def _signal_group(process: subprocess.Popen, signum: int) -> None:
    """Send ``signum`` to the process group that ``process`` leads (nothing when it is gone)."""
    try:
        os.killpg(process.pid, signum)
    except ProcessLookupError:
        pass


def stop_process(process: subprocess.Popen, grace: float = STOP_GRACE_S) -> int:
    """End ``process`` and every process of its group: ``SIGTERM``, then ``SIGKILL`` to what is left
    after at most ``grace`` seconds; returns the exit status of ``process``."""
    _signal_group(process, signal.SIGTERM)
    try:
        process.wait(grace)
    except subprocess.TimeoutExpired:
        pass  # killed below
    finally:  # what is left of the group, also when a second interrupt cuts the wait short
        _signal_group(process, signal.SIGKILL)
    return process.wait()


def die_with_parent() -> None:
    """End this process when the process named by :data:`PARENT_PID_VARIABLE` (the sweep, or the
    Ray worker that started it) ends, even when that one is killed (no variable: nothing to do).

    On Linux the kernel sends ``SIGKILL`` (``prctl(PR_SET_PDEATHSIG)``); elsewhere a daemon thread
    looks at the parent's pid every :data:`PARENT_POLL_S` seconds."""
    parent = os.environ.pop(PARENT_PID_VARIABLE, None)
    if parent is None:
        return
    if sys.platform.startswith("linux"):
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0) != 0:
            raise OSError(ctypes.get_errno(), "prctl(PR_SET_PDEATHSIG) failed")
        _exit_if_orphaned(int(parent))  # the parent may have died before prctl
        return
    threading.Thread(target=_watch_parent, args=(int(parent),), daemon=True).start()


def _exit_if_orphaned(parent: int) -> None:
    """Kill this process when its parent is no longer the process ``parent``."""
    if os.getppid() != parent:
        os.kill(os.getpid(), signal.SIGKILL)


def _watch_parent(parent: int) -> None:
    """Body of the watchdog thread of :func:`die_with_parent`."""
    while True:
        _exit_if_orphaned(parent)
        time.sleep(PARENT_POLL_S)


def run_logged(args: list[str], log_path: str, threads: int | None, cwd: str) -> int:
    """Run ``sb3-hgrn ARGS`` in ``cwd`` to its end, output to ``log_path``; returns its exit status
    (the body of a Ray task). Interrupted (Ray cancels a task with ``KeyboardInterrupt``, which
    arrives between two of Python's steps, so it waits in short sleeps), it stops the process
    (:func:`stop_process`) first, so that no run goes on without its sweep."""
    process, log_file = start_logged(args, Path(log_path), threads, cwd)
    with log_file:
        try:
            while process.poll() is None:
                time.sleep(0.2)
            return process.returncode
        finally:
            if process.returncode is None:
                stop_process(process)


class RunHandle(ABC):
    """One started run."""

    @abstractmethod
    def poll(self) -> int | None:
        """The exit status once the run has ended, else ``None``."""

    @abstractmethod
    def interrupt(self) -> None:
        """Ask the run to stop, without waiting."""

    @abstractmethod
    def stop(self) -> None:
        """Stop the run (:meth:`interrupt`, then kill what is left after a grace time) and wait, a
        bounded time, for its process to end."""


class Backend(ABC):
    """Starts runs (see the module's docstring)."""

    name: str

    @abstractmethod
    def start(self, args: list[str], log_path: Path, threads: int | None) -> RunHandle:
        """Start ``sb3-hgrn ARGS``, its output to ``log_path``, with OpenMP / MKL ``threads``
        (``None``: left as they are)."""

    def default_threads(self, jobs: int) -> int | None:
        """Torch threads per run when none are asked for, with ``jobs`` runs at a time."""
        return 1 if jobs > 1 else None


class LocalProcess(RunHandle):
    """A run in a child process of this one."""

    def __init__(self, process: subprocess.Popen, log_file: Any):
        self.process, self.log_file = process, log_file

    def poll(self) -> int | None:
        status = self.process.poll()
        if status is not None:
            self.log_file.close()
        return status

    def interrupt(self) -> None:
        _signal_group(self.process, signal.SIGTERM)

    def stop(self) -> None:
        stop_process(self.process)
        self.log_file.close()


class LocalBackend(Backend):
    """Every run a child process of this one (``jobs`` at a time on this machine)."""

    name = "local"

    def start(self, args: list[str], log_path: Path, threads: int | None) -> RunHandle:
        return LocalProcess(*start_logged(args, log_path, threads))


class RayTask(RunHandle):
    """A run in a Ray task. A task that fails in Ray itself (its worker or node lost after Ray's
    retries) ends with status -1, the error appended to the run's log."""

    def __init__(self, ray: Any, ref: Any, log_path: Path):
        self.ray, self.ref, self.log_path = ray, ref, log_path

    def poll(self) -> int | None:
        ready, _ = self.ray.wait([self.ref], timeout=0)
        if not ready:
            return None
        try:
            return int(self.ray.get(self.ref))
        except self.ray.exceptions.RayError as error:
            with open(self.log_path, "a", encoding="utf-8") as log_file:
                log_file.write(f"\nRay task failed: {error}\n")
            return -1

    def interrupt(self) -> None:
        self.ray.cancel(self.ref)

    def stop(self) -> None:
        """Cancel the task (``KeyboardInterrupt`` in it, which stops its process); if it has not
        ended ``RAY_CANCEL_GRACE_S`` later (the interrupt lost, or the task stuck), kill its worker,
        whose death ends the process (:func:`die_with_parent`), and wait as long again."""
        self.interrupt()
        if not self._ended(RAY_CANCEL_GRACE_S):
            self.ray.cancel(self.ref, force=True)
            self._ended(RAY_CANCEL_GRACE_S)

    def _ended(self, timeout: float) -> bool:
        """Whether the task ends within ``timeout`` seconds."""
        ready, _ = self.ray.wait([self.ref], timeout=timeout)
        return bool(ready)


def replay_memory(args: list[str]) -> int | None:
    """Bytes of the full replay buffer of the run ``sb3-hgrn ARGS``
    (:func:`~sb3_hgrn.experiments.runs.replay_buffer_bytes`); None for a command other than ``train``."""
    from sb3_hgrn.cli import train_config  # imported here: the command line imports this module
    from sb3_hgrn.experiments.runs import replay_buffer_bytes

    config = train_config(args)
    return None if config is None else replay_buffer_bytes(config)


class RayBackend(Backend):
    """Every run a Ray task with ``num_cpus=cpus_per_run`` and ``num_gpus=gpus_per_run``.

    Connects, when it starts its first run, to the Ray cluster at ``address`` (else the
    ``RAY_ADDRESS`` environment variable, else a new local instance, as ``ray.init`` does), unless
    Ray is initialised in this process already.
    The task runs the process with its node's interpreter, so sb3_hgrn must be installed on every
    node, and in this process's working directory, so that relative run folders mean the same on
    every node: the working directory and the run folders must be on a file system that all nodes
    mount at the same path.

    :param address: address of the cluster's head node (``ray.init(address=...)``).
    Each run's task also reserves the memory of its full replay buffer (Ray's ``memory`` resource,
    in bytes), so that Ray places no more runs on a node than its memory holds.

    :param cpus_per_run: CPUs Ray reserves per run; also the run's torch threads unless given.
    :param gpus_per_run: GPUs Ray reserves per run (``CUDA_VISIBLE_DEVICES`` names them to the run).
    """

    name = "ray"

    def __init__(self, address: str | None = None, cpus_per_run: float = 1.0, gpus_per_run: float = 0.0):
        if cpus_per_run <= 0 or gpus_per_run < 0:
            raise ConfigError(
                f"--cpus-per-run must be positive and --gpus-per-run >= 0, got {cpus_per_run} and "
                f"{gpus_per_run}."
            )
        try:
            import ray
        except ImportError as error:
            raise ConfigError(f"--backend ray needs the ray package: {RAY_INSTALL_COMMAND}") from error
        self.ray, self.address, self.cpus_per_run = ray, address, cpus_per_run
        self._task = ray.remote(num_cpus=cpus_per_run, num_gpus=gpus_per_run)(run_logged)

    def start(self, args: list[str], log_path: Path, threads: int | None) -> RunHandle:
        """Submit the run as a task that reserves, besides its CPUs and GPUs, the ``memory`` its replay
        buffer takes once full (:func:`replay_memory`)."""
        if not self.ray.is_initialized():  # connect at the first run: not at all when none is missing
            self.ray.init(address=self.address)
        log_path = log_path.absolute()
        memory = replay_memory(args)
        task = self._task if memory is None else self._task.options(memory=memory)
        return RayTask(self.ray, task.remote(args, str(log_path), threads, os.getcwd()), log_path)

    def default_threads(self, jobs: int) -> int | None:
        return max(1, int(self.cpus_per_run))


def make_backend(
    name: str = "local",
    address: str | None = None,
    cpus_per_run: float | None = None,
    gpus_per_run: float | None = None,
) -> Backend:
    """The backend called ``name`` (one of :data:`BACKENDS`); ``address`` and the resources per run
    (default 1 CPU, no GPU) apply to ``ray`` only."""
    if name == "local":
        if address is not None or cpus_per_run is not None or gpus_per_run is not None:
            raise ConfigError("--address, --cpus-per-run and --gpus-per-run apply to --backend ray only.")
        return LocalBackend()
    if name == "ray":
        return RayBackend(address, 1.0 if cpus_per_run is None else cpus_per_run, gpus_per_run or 0.0)
    raise ConfigError(f"Unknown backend {name!r}; available: {', '.join(BACKENDS)}.")
