"""Where the sweeps' runs execute: local processes, or Ray tasks on one machine or a cluster.

A backend starts one ``python -m sb3_hgrn ARGS`` process per run, its output going to the run's
log file, and hands back a :class:`RunHandle` that the job loop
(:func:`sb3_hgrn.experiments.table1.run_jobs`) polls. Both backends run the very same command, so
finished runs are skipped, killed runs resume from their checkpoints and run folders are locked
alike (:mod:`sb3_hgrn.experiments.lock`).

- :class:`LocalBackend`: a child process of the sweep's own process.
- :class:`RayBackend`: a Ray remote task (with ``num_cpus`` / ``num_gpus``) that starts the process
  on whichever node Ray places it; the run folders must then lie on a file system that every node
  mounts at the same path. Ray is imported only when this backend is built
  (``pip install 'sb3_hgrn[ray]'``).
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from abc import ABC, abstractmethod
from pathlib import Path
from typing import Any

from sb3_hgrn.experiments.config import ConfigError

BACKENDS = ("local", "ray")
RAY_INSTALL_COMMAND = "pip install 'sb3_hgrn[ray]'"


def python_command(args: list[str]) -> list[str]:
    """``[sys.executable, "-m", "sb3_hgrn", *args]``: the command line of ``sb3-hgrn ARGS`` with this
    machine's interpreter."""
    return [sys.executable, "-m", "sb3_hgrn", *args]


def child_env(threads: int | None) -> dict[str, str]:
    """Environment of a run's process: this package importable, OpenMP / MKL threads capped if asked."""
    env = dict(os.environ)
    package_parent = str(Path(__file__).resolve().parents[2])
    env["PYTHONPATH"] = os.pathsep.join(p for p in (package_parent, env.get("PYTHONPATH", "")) if p)
    if threads is not None:
        for name in ("OMP_NUM_THREADS", "MKL_NUM_THREADS"):
            env[name] = str(threads)
    return env


def start_logged(
    args: list[str], log_path: Path, threads: int | None, cwd: str | None = None
) -> tuple[subprocess.Popen, Any]:
    """Start ``sb3-hgrn ARGS`` in the directory ``cwd`` (default this process's) with stdout and
    stderr appended to ``log_path`` (a resumed run keeps the log of its killed attempt):
    ``(process, open log file)``."""
    log_file = open(log_path, "a", encoding="utf-8")  # noqa: SIM115
    process = subprocess.Popen(
        python_command(args), stdout=log_file, stderr=subprocess.STDOUT, env=child_env(threads), cwd=cwd
    )
    return process, log_file


def run_logged(args: list[str], log_path: str, threads: int | None, cwd: str) -> int:
    """Run ``sb3-hgrn ARGS`` in ``cwd`` to its end, output to ``log_path``; returns its exit status
    (the body of a Ray task). Interrupted (Ray cancels a task with ``KeyboardInterrupt``, which
    arrives between two of Python's steps, so it waits in short sleeps), it stops the process first,
    so that no run goes on without its sweep."""
    process, log_file = start_logged(args, Path(log_path), threads, cwd)
    with log_file:
        try:
            while process.poll() is None:
                time.sleep(0.2)
            return process.returncode
        except KeyboardInterrupt:
            process.terminate()
            process.wait()
            raise


class RunHandle(ABC):
    """One started run."""

    @abstractmethod
    def poll(self) -> int | None:
        """The exit status once the run has ended, else ``None``."""

    @abstractmethod
    def stop(self) -> None:
        """Stop the run and wait for its process to end."""


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

    def stop(self) -> None:
        self.process.terminate()
        self.process.wait()
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

    def stop(self) -> None:
        self.ray.cancel(self.ref)
        try:
            self.ray.get(self.ref)
        except self.ray.exceptions.RayError:
            pass  # cancelled, as asked


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
        if not self.ray.is_initialized():  # connect at the first run: not at all when none is missing
            self.ray.init(address=self.address)
        log_path = log_path.absolute()
        return RayTask(self.ray, self._task.remote(args, str(log_path), threads, os.getcwd()), log_path)

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
