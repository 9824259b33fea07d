"""Table 1's robust statistics from its run folders (rliable, see :mod:`sb3_hgrn.experiments.stats`).

A run's score is its mean evaluation team return. Written beside ``table1.csv`` and ``table1.md``:

- ``table1_aggregate.csv``: per method, the IQM of its runs' normalised scores over all envs, with its
  stratified-bootstrap interval;
- ``table1_profile.png`` and ``table1_profile.csv``: performance profiles of the same normalised scores;
- ``table1_improvement.csv``: the probability of improvement of the key comparisons, with intervals:
  each of the paper's methods against each of its ablations, per env and over all envs, and on CTC
  each HGAT model against its homogeneous-attention twin, from the runs of ``sb3-hgrn figure ctc`` in
  the same folder where they exist.

Normalisation, per env: ``(score - random) / (reference - random)``, where ``random`` is the Random
row's mean over seeds and ``reference`` the mean over seeds of :data:`REFERENCE_PRESET` (DQN), a method
fixed before any run is seen, so that Random scores about 0 and DQN 1. The upper anchor is not the best
method's mean, which would pull the best method toward 1 by construction. An env without a Random
run, without a DQN run or where DQN does not beat Random is left out. Across envs, a method's runs
are the seeds it has finished on every env.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from sb3_hgrn.common.files import atomic_write, write_csv_atomically
from sb3_hgrn.experiments.cells import format_interval, interval_columns, rounded
from sb3_hgrn.experiments.config import RANDOM_POLICY
from sb3_hgrn.experiments.paper import ENV_TITLES, PRESET_TITLES
from sb3_hgrn.experiments.run_folder import figure_root, read_eval, run_folder
from sb3_hgrn.experiments.stats import (
    BOOTSTRAP_REPS,
    Profile,
    improvement_interval,
    iqm_interval,
    normalise,
    performance_profiles,
)
from sb3_hgrn.presets import HGAT_TWINS

AGGREGATE_FILE = "table1_aggregate.csv"
IMPROVEMENT_FILE = "table1_improvement.csv"
PROFILE_FILE = "table1_profile.png"
ABLATED_METHODS = ("soft_hgrn", "sac_hgrn")
"""The paper's methods compared with each of their ablations (``<method>-G``, ``-R``, ``-S``)."""
ALL_ENVS = "all"
CTC_ENV = "ctc_v0"
PROFILE_POINTS = 101
REFERENCE_PRESET = "dqn"
"""The method whose mean is the upper anchor (1) of the normalisation on every env: the paper's plain
baseline (independent deep Q-learning, no communication), chosen before any result; it is the same
method on every env and does not depend on which method comes out best. (The paper's own Table 1
scores are not used: they were measured at other env sizes and budgets, on other scales.)"""

Scores = dict[int, float]
"""Score per seed of one (env, preset)."""
Case = tuple[str, str, str, np.ndarray, np.ndarray]
"""A comparison: ``(x, y, env, (runs, envs) scores of x, those of y)``."""


@dataclass(frozen=True)
class Anchor:
    """The normalisation of one env: ``random`` maps to 0, ``reference`` (the mean of
    :data:`REFERENCE_PRESET`) to 1."""

    env: str
    random: float
    reference: float


@dataclass
class RobustTables:
    """Table 1's statistics across envs and its key comparisons (rows as written to the CSV files)."""

    anchors: list[Anchor]
    aggregate: list[dict[str, Any]]
    improvement: list[dict[str, Any]]
    profiles: dict[str, Profile]


def seed_scores(root: Path, env: str, preset: str, seeds: Sequence[int], budget: str) -> Scores:
    """Mean evaluation team return per seed of the complete runs of ``budget`` under ``root``."""
    evals = {seed: read_eval(run_folder(root, env, preset, seed)) for seed in seeds}
    return {seed: e["mean"] for seed, e in evals.items() if e is not None and e.get("budget") == budget}


def _mean(scores: Scores) -> float:
    return float(np.mean(list(scores.values())))


def column(scores: Scores) -> np.ndarray:
    """``(runs, 1)`` scores of one env."""
    return np.array(list(scores.values()), dtype=float).reshape(-1, 1)


def across_envs(by_env: Sequence[Scores]) -> np.ndarray:
    """``(runs, envs)`` scores of the seeds finished on every env (no rows when there is none)."""
    seeds = sorted(set.intersection(*(set(scores) for scores in by_env)))
    values = [[scores[seed] for scores in by_env] for seed in seeds]
    return np.array(values, dtype=float).reshape(len(seeds), len(by_env))


def _title(preset: str) -> str:
    return PRESET_TITLES.get(preset, preset)


def _two_decimals(value: float) -> str:
    return f"{value:.2f}"


def ablation_pairs(presets: Sequence[str]) -> list[tuple[str, str]]:
    """``(method, ablation)`` for each of the paper's methods in ``presets`` and each of its ablations
    there."""
    return [
        (method, preset)
        for method in ABLATED_METHODS
        if method in presets
        for preset in presets
        if preset.startswith(f"{method}-")
    ]


def twin_pairs() -> list[tuple[str, str]]:
    """``(HGAT model, its homogeneous-attention twin)`` as the CTC figure trains them."""
    return [(original, twin) for twin, original in HGAT_TWINS.items()]


def anchors(scores: Mapping[tuple[str, str], Scores], envs: Sequence[str]) -> list[Anchor]:
    """The normalisation of every env that has a Random run and a :data:`REFERENCE_PRESET` run whose
    mean is above Random's (see the module)."""
    found = []
    for env in envs:
        random, reference = scores[(env, RANDOM_POLICY)], scores[(env, REFERENCE_PRESET)]
        if random and reference and _mean(reference) > _mean(random):
            found.append(Anchor(env, _mean(random), _mean(reference)))
    return found


def normalised_scores(
    scores: Mapping[tuple[str, str], Scores], env_anchors: Sequence[Anchor], presets: Sequence[str]
) -> dict[str, np.ndarray]:
    """``(runs, envs)`` normalised scores per preset over the anchored envs (presets without a seed
    finished on all of them are left out)."""
    low = np.array([anchor.random for anchor in env_anchors])
    high = np.array([anchor.reference for anchor in env_anchors])
    matrices = {p: across_envs([scores[(anchor.env, p)] for anchor in env_anchors]) for p in presets}
    return {p: normalise(matrix, low, high) for p, matrix in matrices.items() if len(matrix)}


def aggregate_rows(normalised: Mapping[str, np.ndarray], reps: int) -> list[dict[str, Any]]:
    """Per preset: IQM of its normalised scores with its interval, and the runs it is computed from."""
    return [
        {
            "preset": preset,
            **interval_columns("normalised_iqm", iqm_interval(matrix, reps)),
            "runs_per_env": len(matrix),
            "envs": matrix.shape[1],
        }
        for preset, matrix in normalised.items()
    ]


def comparison_cases(
    scores: Mapping[tuple[str, str], Scores],
    ctc: Mapping[str, Scores],
    envs: Sequence[str],
    presets: Sequence[str],
) -> list[Case]:
    """Every key comparison, per env, over all envs (with more than one env) and on CTC."""
    cases: list[Case] = []
    for x, y in ablation_pairs(presets):
        cases += [(x, y, env, column(scores[(env, x)]), column(scores[(env, y)])) for env in envs]
        if len(envs) > 1:
            both = [across_envs([scores[(env, p)] for env in envs]) for p in (x, y)]
            cases.append((x, y, ALL_ENVS, *both))
    cases += [(x, y, CTC_ENV, column(ctc[x]), column(ctc[y])) for x, y in twin_pairs()]
    return cases


def improvement_rows(cases: Sequence[Case], reps: int) -> list[dict[str, Any]]:
    """Probability that a run of x beats one of y, with its interval, for every case with runs of both."""
    return [
        {
            "x": x,
            "y": y,
            "env": env,
            **interval_columns("probability", improvement_interval(scores_x, scores_y, reps)),
            "runs_x": len(scores_x),
            "runs_y": len(scores_y),
        }
        for x, y, env, scores_x, scores_y in cases
        if len(scores_x) and len(scores_y)
    ]


def profile_taus(normalised: Mapping[str, np.ndarray]) -> np.ndarray:
    """Thresholds of the profiles: from the lowest normalised score (or 0) to the highest (or 1)."""
    values = np.concatenate([matrix.ravel() for matrix in normalised.values()])
    return np.linspace(min(0.0, values.min()), max(1.0, values.max()), PROFILE_POINTS)


def robust_tables(
    results: Path,
    budget: str,
    envs: Sequence[str],
    presets: Sequence[str],
    seeds: Sequence[int],
    reps: int = BOOTSTRAP_REPS,
) -> RobustTables:
    """Table 1's statistics across envs and key comparisons from the runs under ``results``."""
    root = results / "table1"
    anchoring = [*presets, RANDOM_POLICY, REFERENCE_PRESET]
    scores = {(env, p): seed_scores(root, env, p, seeds, budget) for env in envs for p in anchoring}
    ctc_root = figure_root(results, "ctc")
    ctc = {p: seed_scores(ctc_root, CTC_ENV, p, seeds, budget) for pair in twin_pairs() for p in pair}
    env_anchors = anchors(scores, envs)
    normalised = normalised_scores(scores, env_anchors, presets) if env_anchors else {}
    return RobustTables(
        anchors=env_anchors,
        aggregate=aggregate_rows(normalised, reps),
        improvement=improvement_rows(comparison_cases(scores, ctc, envs, presets), reps),
        profiles=performance_profiles(normalised, profile_taus(normalised), reps) if normalised else {},
    )


def profile_rows(profiles: Mapping[str, Profile]) -> list[dict[str, Any]]:
    """The plotted numbers of the profiles: one row per preset and threshold."""
    return [
        {"preset": preset, "tau": tau, "fraction": fraction, "fraction_low": low, "fraction_high": high}
        for preset, profile in profiles.items()
        for tau, fraction, low, high in zip(
            profile.taus, profile.fraction, profile.low, profile.high, strict=True
        )
    ]


def draw_profiles(profiles: Mapping[str, Profile], env_anchors: Sequence[Anchor]) -> Figure:
    """The performance profiles, drawn with rliable's ``plot_performance_profiles``."""
    from rliable import plot_utils

    figure = Figure(figsize=(8, 5), layout="constrained")
    FigureCanvasAgg(figure)
    axis = figure.add_subplot()
    plot_utils.plot_performance_profiles(
        {_title(preset): profile.fraction for preset, profile in profiles.items()},
        next(iter(profiles.values())).taus,
        performance_profile_cis={
            _title(preset): (profile.low, profile.high) for preset, profile in profiles.items()
        },
        ax=axis,
        xlabel=f"normalised score tau (0: Random, 1: {_title(REFERENCE_PRESET)}, per env)",
        ylabel="fraction of runs with score > tau",
        labelsize="medium",
        ticklabelsize="medium",
    )
    axis.legend(fontsize=7, ncol=2)
    envs = ", ".join(ENV_TITLES.get(anchor.env, anchor.env) for anchor in env_anchors)
    axis.set_title(
        f"Performance profiles over the runs of {envs}\nshaded: 95 % bootstrap intervals", fontsize=10
    )
    return figure


def write_robust_tables(results: Path, tables: RobustTables) -> None:
    """Write the aggregate, the comparisons and the profiles (PNG and CSV) into ``results``."""
    write_csv_atomically(results / AGGREGATE_FILE, rounded(tables.aggregate))
    write_csv_atomically(results / IMPROVEMENT_FILE, rounded(tables.improvement))
    if tables.profiles:
        profile = results / PROFILE_FILE
        with atomic_write(profile, "wb") as file:
            draw_profiles(tables.profiles, tables.anchors).savefig(file, format="png", dpi=110)
        write_csv_atomically(profile.with_suffix(".csv"), rounded(profile_rows(tables.profiles)))


def _probability_cell(rows: Mapping[tuple[str, str, str], dict[str, Any]], key: tuple[str, str, str]) -> str:
    row = rows.get(key)
    if row is None:
        return "-"
    return format_interval(row["probability"], row["probability_low"], row["probability_high"], _two_decimals)


def improvement_markdown(
    tables: RobustTables, columns: Sequence[str], pairs: Sequence[tuple[str, str]]
) -> list[str]:
    """A table of P(x > y) [95 % CI], one row per pair of ``pairs``, one column per env of ``columns``."""
    rows = {(row["x"], row["y"], row["env"]): row for row in tables.improvement}
    titles = [ENV_TITLES.get(env, "all envs" if env == ALL_ENVS else env) for env in columns]
    lines = ["| X vs Y | " + " | ".join(titles) + " |", "|---|" + "---|" * len(columns)]
    for x, y in pairs:
        cells = [_probability_cell(rows, (x, y, env)) for env in columns]
        lines.append(f"| {_title(x)} vs {_title(y)} | " + " | ".join(cells) + " |")
    return lines


def aggregate_markdown(tables: RobustTables) -> list[str]:
    """The markdown of the normalised IQM across envs: its anchors and one row per method."""
    reference = _title(REFERENCE_PRESET)
    if not tables.anchors:
        return [f"No env has a Random run and a {reference} run above it: nothing to normalise."]
    anchored = "; ".join(
        f"{ENV_TITLES.get(a.env, a.env)}: 0 = Random {a.random:.1f}, 1 = {reference} {a.reference:.1f}"
        for a in tables.anchors
    )
    lines = [
        f"Scores normalised per env, `(score - Random) / ({reference} - Random)` with the means over "
        f"seeds of the Random row and of {reference}, the reference fixed before any run ({anchored}); "
        f"{reference}'s own row is about 1 by construction. IQM over the runs of all these envs "
        "with its 95 % stratified-bootstrap interval (seeds finished on every env); performance "
        f"profiles in `{PROFILE_FILE}`.",
        "",
        "| Algorithm | normalised IQM [95 % CI] | runs per env |",
        "|---|---|---|",
    ]
    for row in tables.aggregate:
        cell = format_interval(
            row["normalised_iqm"], row["normalised_iqm_low"], row["normalised_iqm_high"], _two_decimals
        )
        lines.append(f"| {_title(row['preset'])} | {cell} | {row['runs_per_env']} |")
    return lines


def improvement_section(tables: RobustTables, envs: Sequence[str], presets: Sequence[str]) -> list[str]:
    """The markdown of the key comparisons: ablations per env and over all envs, CTC twins where they
    ran (no lines when there is no comparison)."""
    ablations = ablation_pairs(presets)
    compared_on_ctc = {(row["x"], row["y"]) for row in tables.improvement if row["env"] == CTC_ENV}
    twins = [pair for pair in twin_pairs() if pair in compared_on_ctc]
    if not (ablations or twins):
        return []
    lines = [
        "",
        "## Probability of improvement",
        "",
        "P(X > Y): the probability that a run of X scores above a run of Y on the same env (ties count "
        "half; over all envs: the average over envs), with its 95 % bootstrap interval. 0.5: no difference.",
    ]
    if ablations:
        columns = [*envs, ALL_ENVS] if len(envs) > 1 else list(envs)
        lines += ["", "The paper's methods against each of their ablations:", ""]
        lines += improvement_markdown(tables, columns, ablations)
    if twins:
        lines += [
            "",
            "On CTC, HGAT models against their homogeneous-attention twins (the runs of "
            "`sb3-hgrn figure ctc` in `figures/ctc`):",
            "",
            *improvement_markdown(tables, [CTC_ENV], twins),
        ]
    return lines


def markdown_sections(tables: RobustTables, envs: Sequence[str], presets: Sequence[str]) -> list[str]:
    """The markdown of the statistics across envs and of the key comparisons."""
    return [
        "",
        "## Across envs",
        "",
        *aggregate_markdown(tables),
        *improvement_section(tables, envs, presets),
    ]
