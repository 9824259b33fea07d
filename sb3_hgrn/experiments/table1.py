"""The paper's Table 1 sweep: every (env, preset, seed) trained and evaluated in its own process.

The processes run on a backend (:mod:`sb3_hgrn.experiments.backends`): this machine's, or Ray tasks.

Runs go to ``<folder>/table1/<env>/<preset>/seed_<seed>/`` (see :mod:`sb3_hgrn.experiments.run_folder`);
a run whose folder holds a complete ``eval.json`` is skipped, so a killed sweep resumes where it
stopped. Each (env, seed) also gets a uniformly random policy evaluated the same way, without
training (``<env>/random/seed_<seed>/``), as the tables' anchor row. After every finished run the
tables ``<folder>/table1.csv`` and ``<folder>/table1.md`` are rewritten from the run folders; when the
sweep ends they get the robust statistics too (:mod:`sb3_hgrn.experiments.table1_stats`).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from sb3_hgrn.common.files import write_csv_atomically, write_text_atomically
from sb3_hgrn.experiments.backends import Backend, LocalBackend
from sb3_hgrn.experiments.cells import (
    format_cell,
    format_interval,
    format_number,
    iqm_columns,
    mean_std,
    rounded,
)
from sb3_hgrn.experiments.config import (
    RANDOM_POLICY,
    ConfigError,
    check_budget_name,
    check_env_name,
    check_preset_name,
    load_hyperparams,
    random_policy_config,
)
from sb3_hgrn.experiments.jobs import Job, check_budget_of_folder, plan_jobs, print_line, run_jobs, train_args
from sb3_hgrn.experiments.paper import (
    ENV_TITLES,
    PAPER_EVAL_EPISODES,
    PAPER_SEEDS,
    PAPER_SIZES,
    PAPER_TABLE1,
    PRESET_TITLES,
    TABLE1_ENVS,
)
from sb3_hgrn.experiments.run_folder import read_eval, run_folder
from sb3_hgrn.experiments.runs import evaluate_random_policy
from sb3_hgrn.experiments.stats import BOOTSTRAP_REPS, rliable_modules
from sb3_hgrn.experiments.table1_stats import (
    RobustTables,
    markdown_sections,
    robust_tables,
    write_robust_tables,
)
from sb3_hgrn.presets import TABLE1

COMPARISON_EPSILON = "0.3"
"""The epsilon of the authors' evaluation mode, reported beside the plain policy."""


def run_sweep(
    budget: str,
    n_seeds: int = 3,
    folder: str | os.PathLike = "results",
    jobs: int = 1,
    presets: Sequence[str] | None = None,
    envs: Sequence[str] | None = None,
    threads: int | None = None,
    save_freq: int | None = None,
    log: Callable[[str], None] = print_line,
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
    root: Path,
    budget: str,
    envs: Sequence[str],
    seeds: Sequence[int],
    log: Callable[[str], None] = print_line,
) -> None:
    """Evaluate the uniformly random policy for every (env, seed) whose anchor run is missing."""
    for env in envs:
        for seed in seeds:
            folder = run_folder(root, env, RANDOM_POLICY, seed)
            if read_eval(folder) is None:
                done = evaluate_random_policy(random_policy_config(env, budget, seed), folder)
                log(f"{env} random policy seed {seed}: team return {done['mean']:.1f} +- {done['std']:.1f}")


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
