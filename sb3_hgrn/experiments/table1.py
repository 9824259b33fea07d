"""The paper's Table 1 sweep: every (env, preset, seed) trained and evaluated in its own process.

The processes run on a backend (:mod:`sb3_hgrn.experiments.backends`): this machine's, or Ray tasks.

Runs go to ``<folder>/table1/<env>/<preset>/seed_<seed>/`` (see :mod:`sb3_hgrn.experiments.runs`);
a run whose folder holds a complete ``eval.json`` is skipped, so a killed sweep resumes where it
stopped. Each (env, seed) also gets a uniformly random policy evaluated the same way, without
training (``<env>/random/seed_<seed>/``), as the tables' anchor row. After every finished run the
tables ``<folder>/table1.csv`` and ``<folder>/table1.md`` are rewritten from the run folders; when the
sweep ends they get the robust statistics too (:mod:`sb3_hgrn.experiments.table1_stats`).
"""

from __future__ import annotations

import os
import re
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from sb3_hgrn.common.files import write_csv_atomically, write_text_atomically
from sb3_hgrn.experiments.backends import Backend, LocalBackend, RunHandle
from sb3_hgrn.experiments.config import (
    RANDOM_POLICY,
    ConfigError,
    check_budget_name,
    check_env_name,
    check_preset_name,
    load_hyperparams,
    random_policy_config,
)
from sb3_hgrn.experiments.lock import lock_holder
from sb3_hgrn.experiments.paper import (
    ENV_TITLES,
    PAPER_EVAL_EPISODES,
    PAPER_SEEDS,
    PAPER_SIZES,
    PAPER_TABLE1,
    PRESET_TITLES,
    TABLE1_ENVS,
)
from sb3_hgrn.experiments.runs import evaluate_random_policy, read_eval, run_folder
from sb3_hgrn.experiments.stats import BOOTSTRAP_REPS, iqm_interval, rliable_modules
from sb3_hgrn.experiments.table1_stats import (
    RobustTables,
    format_interval,
    interval_columns,
    markdown_sections,
    robust_tables,
    rounded,
    write_robust_tables,
)
from sb3_hgrn.presets import TABLE1

LOG_FILE = "train.log"
COMPARISON_EPSILON = "0.3"
"""The epsilon of the authors' evaluation mode, reported beside the plain policy."""


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


def _print(message: str) -> None:
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


def run_sweep(
    budget: str,
    n_seeds: int = 3,
    folder: str | os.PathLike = "results",
    jobs: int = 1,
    presets: Sequence[str] | None = None,
    envs: Sequence[str] | None = None,
    threads: int | None = None,
    save_freq: int | None = None,
    log: Callable[[str], None] = _print,
    backend: Backend | None = None,
) -> list[Job]:
    """Train and evaluate every missing run, ``jobs`` processes at a time, and write the tables.

    :param threads: torch threads per process (default: the backend's, for the local one 1 when
        ``jobs > 1``, else torch's own).
    :param save_freq: checkpoint every this many agent-steps, so that a killed run resumes from its
        last checkpoint (default: a killed run restarts from scratch).
    :param backend: where the runs execute (default: local processes).
    :return: the runs that failed.
    """
    check_budget_name(budget)
    envs, presets = list(envs or TABLE1_ENVS), list(presets or TABLE1)
    for env in envs:
        check_env_name(env)
        load_hyperparams(env)
    for preset in presets:
        check_preset_name(preset)
    if n_seeds < 1 or jobs < 1:
        raise ConfigError(f"--seeds and --jobs must be >= 1, got {n_seeds} and {jobs}.")
    rliable_modules()  # the tables' statistics need it: fail before training, not after
    backend = backend or LocalBackend()
    threads = backend.default_threads(jobs) if threads is None else threads
    results, root = Path(folder), Path(folder) / "table1"
    check_budget_of_folder(root, budget)
    seeds = list(range(n_seeds))
    all_jobs = plan_jobs(root, envs, presets, seeds)
    todo = [job for job in all_jobs if read_eval(job.folder) is None]
    evaluate_random_anchors(root, budget, envs, seeds, log)
    log(
        f"Table 1, budget {budget}: {len(all_jobs)} runs, {len(all_jobs) - len(todo)} already done, "
        f"{len(todo)} to run, {jobs} at a time ({backend.name} backend)"
    )
    failed = run_jobs(
        todo,
        lambda job: train_args(job, budget, root, threads, save_freq),
        jobs,
        threads,
        log,
        on_finished=lambda: write_tables(results, budget, envs, presets, seeds, robust=False),
        backend=backend,
    )
    write_tables(results, budget, envs, presets, seeds)
    log(f"Wrote {results / 'table1.csv'} and {results / 'table1.md'}")
    return failed


def evaluate_random_anchors(
    root: Path, budget: str, envs: Sequence[str], seeds: Sequence[int], log: Callable[[str], None] = _print
) -> None:
    """Evaluate the uniformly random policy for every (env, seed) whose anchor run is missing."""
    for env in envs:
        for seed in seeds:
            folder = run_folder(root, env, RANDOM_POLICY, seed)
            if read_eval(folder) is None:
                done = evaluate_random_policy(random_policy_config(env, budget, seed), folder)
                log(f"{env} random policy seed {seed}: team return {done['mean']:.1f} +- {done['std']:.1f}")


def run_jobs(
    todo: Sequence[Job],
    args: Callable[[Job], list[str]],
    jobs: int = 1,
    threads: int | None = None,
    log: Callable[[str], None] = _print,
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


def mean_std(values: list[float]) -> tuple[float | None, float | None]:
    """Mean and (population) standard deviation; ``None`` for no values, and std ``None`` for one."""
    if not values:
        return None, None
    return float(np.mean(values)), float(np.std(values)) if len(values) > 1 else None


def iqm_columns(values: list[float], reps: int | None) -> dict[str, float | None]:
    """``iqm``, ``iqm_low``, ``iqm_high`` of one cell's seed scores (``None`` without scores or ``reps``)."""
    interval = iqm_interval(np.array(values).reshape(-1, 1), reps) if values and reps else None
    return interval_columns("iqm", interval)


def collect_rows(
    root: Path, envs: Sequence[str], presets: Sequence[str], seeds: Sequence[int], reps: int | None = None
) -> list[dict[str, Any]]:
    """One row per env x preset from the complete runs under ``root``.

    :param reps: bootstrap resamples of the IQM intervals (``None``: the IQM columns are left empty).
    """
    rows = []
    for env in envs:
        for preset in presets:
            evals = [e for e in (read_eval(run_folder(root, env, preset, seed)) for seed in seeds) if e]
            scores = [e["mean"] for e in evals]
            mean, std = mean_std(scores)
            eps = [
                e["epsilon_evaluations"][COMPARISON_EPSILON]["mean"]
                for e in evals
                if COMPARISON_EPSILON in e.get("epsilon_evaluations", {})
            ]
            eps_mean, eps_std = mean_std(eps)
            paper = PAPER_TABLE1.get(preset, {}).get(env, (None, None))
            rows.append(
                {
                    "env": env,
                    "preset": preset,
                    **iqm_columns(scores, reps),
                    "mean": mean,
                    "std": std,
                    "seeds_done": len(evals),
                    "seeds": len(seeds),
                    "seed_means": " ".join(f"{e['mean']:.2f}" for e in evals),
                    "eval_episodes": min((e["n_episodes"] for e in evals), default=None),
                    "n_agents": evals[0]["n_agents"] if evals else None,
                    "agent_steps": evals[0]["agent_steps"] if evals else None,
                    "env_steps": evals[0]["env_steps"] if evals else None,
                    "wall_time_s": round(sum(e["wall_time_s"] for e in evals), 1) if evals else None,
                    "eps_0.3_mean": eps_mean,
                    "eps_0.3_std": eps_std,
                    "paper_mean": paper[0],
                    "paper_std": paper[1],
                }
            )
    return rows


def write_tables(
    results: Path,
    budget: str,
    envs: Sequence[str],
    presets: Sequence[str],
    seeds: Sequence[int],
    robust: bool = True,
    reps: int = BOOTSTRAP_REPS,
) -> list[dict[str, Any]]:
    """Write ``table1.csv`` and ``table1.md`` into ``results`` from its run folders.

    :param robust: also the IQM intervals, the statistics across envs and the key comparisons
        (:mod:`sb3_hgrn.experiments.table1_stats`, needs rliable); without, the IQM columns stay empty.
    :param reps: bootstrap resamples per interval.
    """
    results.mkdir(parents=True, exist_ok=True)
    rows = collect_rows(results / "table1", envs, [*presets, RANDOM_POLICY], seeds, reps if robust else None)
    write_csv_atomically(results / "table1.csv", rounded(rows, 2))
    tables = robust_tables(results, budget, envs, presets, seeds, reps) if robust else None
    if tables is not None:
        write_robust_tables(results, tables)
    write_text_atomically(results / "table1.md", markdown(rows, budget, envs, presets, seeds, tables))
    return rows


def format_number(value: float) -> str:
    return f"{value:.0f}" if abs(value) >= 100 else f"{value:.1f}"


def format_cell(mean: float | None, std: float | None) -> str:
    """``mean +- std``, the mean alone when there is no spread to show, ``-`` when missing."""
    if mean is None:
        return "-"
    return format_number(mean) if std is None else f"{format_number(mean)} +- {format_number(std)}"


def markdown(
    rows: list[dict[str, Any]],
    budget: str,
    envs: Sequence[str],
    presets: Sequence[str],
    seeds: Sequence[int],
    tables: RobustTables | None = None,
) -> str:
    """Our Table 1 beside the paper's, with the budget, env sizes and evaluation protocol, and the
    robust statistics of ``tables`` (when given)."""
    by_key = {(row["env"], row["preset"]): row for row in rows}
    smaller = budget != "paper"
    lines = [
        f"# Table 1 reproduced with sb3_hgrn: budget `{budget}`",
        "",
        "Team return (all agents' rewards summed over an episode); a run's score is its mean evaluation "
        "return. **IQM [95 % CI]**: interquartile mean of the runs' scores with its 95 % "
        f"stratified-bootstrap confidence interval over runs (rliable, {BOOTSTRAP_REPS:,} resamples; with "
        "fewer than 4 seeds nothing is trimmed, so it is the mean). **mean +- std**: over seeds of the "
        f"runs' scores ({len(seeds)} seed(s) planned; a cell with fewer seeds done shows `(done/planned)`, "
        "a single seed no spread). "
        f"**paper**: Table 1 of Ye et al. (AAAI 2022), mean +- std over {PAPER_SEEDS} runs of "
        f"{PAPER_EVAL_EPISODES:,} test episodes each. `-`: run missing.",
        "",
        "Evaluation protocol: after training, the plain policy (actions sampled from stochastic "
        "policies, greedy for the deterministic ones: DQN, CommNet, DGN and the -S variants) on fresh env "
        "copies seeded `seed + 1000`; the second table mixes in a uniformly random valid action per agent "
        f"with probability {COMPARISON_EPSILON} (the authors' code's evaluation mode). **Random**: uniformly "
        "random valid actions on the same evaluation episodes, without training (no figure in the paper's "
        "table).",
        "",
    ]
    if smaller:
        lines += [
            f"**The env sizes and training budgets of budget `{budget}` are smaller than the paper's** "
            "(below), so the absolute numbers are not comparable with the paper's; compare orderings "
            "and gaps.",
            "",
        ]
    lines += [
        "| env | sizes (this budget) | agent-steps | env steps | eval episodes / seed | paper's setting |",
        "|---|---|---|---|---|---|",
    ]
    for env in envs:
        section = load_hyperparams(env)["budgets"][budget]
        done = [
            row
            for row in rows
            if row["env"] == env and row["preset"] != RANDOM_POLICY and row["agent_steps"] is not None
        ]
        agent_steps = done[0]["agent_steps"] if done else section["total_timesteps"]
        env_steps = f"{done[0]['env_steps']:,}" if done else "-"
        description = section.get("description") or str(section.get("env_kwargs", {}))
        copies = f"{section['n_envs']} env cop{'y' if section['n_envs'] == 1 else 'ies'} while training"
        lines.append(
            f"| {ENV_TITLES.get(env, env)} | {description}; {copies} "
            f"| {agent_steps:,} | {env_steps} | {section['eval_episodes']} | {PAPER_SIZES.get(env, '-')} |"
        )
    header = " | ".join(f"{ENV_TITLES.get(env, env)} IQM [95 % CI] | mean +- std | paper" for env in envs)
    lines += ["", f"| Algorithm | {header} |", "|---|" + "---|---|---|" * len(envs)]
    for preset in [*presets, RANDOM_POLICY]:
        cells = []
        for env in envs:
            row = by_key[(env, preset)]
            ours = format_cell(row["mean"], row["std"])
            if row["seeds_done"] and row["seeds_done"] < len(seeds):
                ours += f" ({row['seeds_done']}/{len(seeds)})"
            paper = "-" if row["paper_mean"] is None else f"{row['paper_mean']:.0f} +- {row['paper_std']:.0f}"
            cells += [
                format_interval(row["iqm"], row["iqm_low"], row["iqm_high"], format_number),
                ours,
                paper,
            ]
        lines.append(f"| {PRESET_TITLES.get(preset, preset)} | " + " | ".join(cells) + " |")
    if tables is None:
        lines += ["", "The IQM intervals and the robust statistics are computed when the sweep ends."]
    lines += [
        "",
        f"With epsilon = {COMPARISON_EPSILON} random actions (ours only):",
        "",
        "| Algorithm | " + " | ".join(ENV_TITLES.get(env, env) for env in envs) + " |",
        "|---|" + "---|" * len(envs),
    ]
    for preset in presets:
        cells = [
            format_cell(by_key[(env, preset)]["eps_0.3_mean"], by_key[(env, preset)]["eps_0.3_std"])
            for env in envs
        ]
        lines.append(f"| {PRESET_TITLES.get(preset, preset)} | " + " | ".join(cells) + " |")
    if tables is not None:
        lines += markdown_sections(tables, envs, presets)
    wall = sum(row["wall_time_s"] or 0.0 for row in rows)
    lines += [
        "",
        f"Summed wall time of the runs done: {wall / 60:.1f} min (per-run figures in table1.csv).",
        "",
    ]
    return "\n".join(lines)
