"""Running ``sb3-hgrn`` jobs as processes: one (env, preset, seed) run each, ``jobs`` at a time on a
backend (:mod:`sb3_hgrn.experiments.backends`), each writing its ``train.log`` into its run folder.
The sweeps (Table 1, the figures, :mod:`sb3_hgrn.experiments.sweep`) plan their jobs and run them here.
"""

from __future__ import annotations

import re
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

from sb3_hgrn.experiments.backends import Backend, LocalBackend, RunHandle
from sb3_hgrn.experiments.config import ConfigError
from sb3_hgrn.experiments.lock import lock_holder
from sb3_hgrn.experiments.run_folder import read_eval, run_folder

LOG_FILE = "train.log"


@dataclass
class Job:
    """One (env, preset, seed) run of a sweep, with extra ``train`` arguments (e.g. ``--param ...``)."""

    env: str
    preset: str
    seed: int
    folder: Path
    args: tuple[str, ...] = ()

    def label(self) -> str:
        """How the sweep's log names the run."""
        return " ".join((f"{self.env} {self.preset} seed {self.seed}", *self.args))


def plan_jobs(root: Path, envs: Sequence[str], presets: Sequence[str], seeds: Sequence[int]) -> list[Job]:
    """All runs, seed by seed (a partial sweep then covers the whole table with its first seeds)."""
    return [
        Job(env, preset, seed, run_folder(root, env, preset, seed))
        for seed in seeds
        for env in envs
        for preset in presets
    ]


def print_line(message: str) -> None:
    """Print ``message`` at once (the sweeps' default log)."""
    print(message, flush=True)


def train_args(
    job: Job, budget: str, root: Path, threads: int | None, save_freq: int | None = None
) -> list[str]:
    """The ``sb3-hgrn train`` arguments of ``job`` into the run folders under ``root`` (its own
    ``job.args`` last)."""
    command = [
        "train",
        "--env",
        job.env,
        "--preset",
        job.preset,
        "--budget",
        budget,
        "--seed",
        str(job.seed),
        "--folder",
        str(root),
        "--verbose",
        "0",
    ]
    if threads is not None:
        command += ["--threads", str(threads)]
    if save_freq is not None:
        command += ["--save-freq", str(save_freq)]
    return [*command, *job.args]


def check_budget_of_folder(root: Path, budget: str) -> None:
    """Refuse to mix budgets: complete runs under ``root`` must all be of ``budget`` (runs that
    ``--overwrite`` moved aside, ``seed_<n>.replaced-<time>/``, are not runs of the sweep)."""
    for path in root.glob("*/*/seed_*/eval.json"):
        if not re.fullmatch(r"seed_\d+", path.parent.name):
            continue
        done = read_eval(path.parent)
        if done is not None and done.get("budget") != budget:
            raise ConfigError(
                f"{path.parent} holds a run of budget {done.get('budget')!r}, not {budget!r}: "
                "use another --folder for this budget."
            )


def run_jobs(
    todo: Sequence[Job],
    args: Callable[[Job], list[str]],
    jobs: int = 1,
    threads: int | None = None,
    log: Callable[[str], None] = print_line,
    on_finished: Callable[[], object] | None = None,
    backend: Backend | None = None,
) -> list[Job]:
    """Run ``sb3-hgrn`` with the arguments ``args(job)`` for every job of ``todo`` as its own
    process on ``backend`` (default: local processes), ``jobs`` at a time.

    Each process writes its output to its folder's ``train.log``. A job succeeds when its process
    exits with status 0 and leaves a complete ``eval.json``; a failed one is logged with the end of
    its log and the others go on. A job whose folder another process has locked (a run going on
    there, see :mod:`sb3_hgrn.experiments.lock`) is not started and counts as failed. Interrupted
    (Ctrl-C), it stops the runs going on (:func:`stop_runs`) before it raises ``KeyboardInterrupt``.

    :param threads: cap of the processes' OpenMP / MKL threads (``None``: left as they are).
    :param on_finished: called after every finished job, and when interrupted (e.g. to rewrite tables).
    :return: the jobs that failed.
    """
    backend = backend or LocalBackend()
    todo = list(todo)
    failed: list[Job] = []
    running: list[tuple[Job, RunHandle, float]] = []
    finished = 0
    try:
        while todo or running:
            while todo and len(running) < jobs:
                job = todo.pop(0)
                holder = lock_holder(job.folder)
                if holder is not None:  # its train.log belongs to the run going on there
                    failed.append(job)
                    log(f"{job.label()}: SKIPPED, {job.folder} is in use by {holder}")
                    continue
                job.folder.mkdir(parents=True, exist_ok=True)
                running.append((job, backend.start(args(job), job.folder / LOG_FILE, threads), time.time()))
            time.sleep(0.2)
            for entry in list(running):
                job, run, started = entry
                status = run.poll()
                if status is None:
                    continue
                running.remove(entry)
                finished += 1
                done = read_eval(job.folder)
                total = finished + len(todo) + len(running)
                label = f"[{finished}/{total}] {job.label()}"
                if status == 0 and done is not None:
                    log(
                        f"{label}: team return {done['mean']:.1f} +- {done['std']:.1f} "
                        f"({time.time() - started:.0f} s)"
                    )
                else:
                    failed.append(job)
                    log(
                        f"{label}: FAILED (exit {status}); see {job.folder / LOG_FILE}:\n"
                        + _tail(job.folder / LOG_FILE)
                    )
                if on_finished is not None:
                    on_finished()
    except KeyboardInterrupt:
        stop_runs([run for _, run, _ in running])
        if on_finished is not None:
            on_finished()
        raise
    return failed


def stop_runs(runs: Sequence[RunHandle]) -> None:
    """Stop ``runs`` together: every one interrupted first, then each stopped
    (:meth:`~sb3_hgrn.experiments.backends.RunHandle.stop`), so that their grace times overlap."""
    for run in runs:
        run.interrupt()
    for run in runs:
        run.stop()


def _tail(path: Path, lines: int = 15) -> str:
    try:
        return "".join(path.read_text(encoding="utf-8", errors="replace").splitlines(True)[-lines:])
    except OSError:
        return ""
