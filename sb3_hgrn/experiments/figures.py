"""The paper's figures besides Table 1 and the case study, each drawn by one command.

``sb3-hgrn figure NAME --budget B --seeds N`` first trains the runs the figure needs, each as its own
``python -m sb3_hgrn train`` process (on a backend of :mod:`sb3_hgrn.experiments.backends`) into
``<folder>/figures/<NAME>/.../<env>/<preset>/seed_<seed>/``
(:func:`sb3_hgrn.experiments.table1.run_jobs`, so finished runs are skipped exactly as
``reproduce table1`` skips them), then draws the figure from the run folders into a PNG and writes
beside it the plotted numbers (``<out>.csv``) and what produced them (``<out>.json``: the command,
budget, env sizes, agent-steps, seeds and wall time).

- ``ctc``: learning curves on CTC, training team return against agent-steps (mean and std over seeds),
  HGAT models solid, their homogeneous-attention twins dashed in the same colour.
- ``alpha``: alpha, alpha's gradient and the action entropy against its target during Soft-HGRN
  and SAC-HGRN training on Surviving (and SAC-HGRN's actor's entropy), from the runs' TensorBoard
  scalars.
- ``transfer``: every Table 1 method trained on Surviving at the budget's agent count, then evaluated
  at 0.25, 0.5, 1, 2 and 4 times that count on the same map; team return per agent against agents.
- ``p_alpha``: Soft-HGRN's evaluation team return on Surviving for several target-entropy ratios.
"""

from __future__ import annotations

import csv
import json
import os
import shlex
import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from sb3_hgrn.common.files import atomic_write, write_csv_atomically
from sb3_hgrn.experiments.backends import Backend, LocalBackend
from sb3_hgrn.experiments.callbacks import TEAM_RETURNS_FILE
from sb3_hgrn.experiments.config import (
    ConfigError,
    check_budget_name,
    check_preset_name,
    load_hyperparams,
)
from sb3_hgrn.experiments.jobs import Job, check_budget_of_folder, plan_jobs, run_jobs, train_args
from sb3_hgrn.experiments.paper import ENV_TITLES, PRESET_TITLES
from sb3_hgrn.experiments.run_folder import (
    CONFIG_FILE,
    MODEL_FILE,
    TENSORBOARD_DIR,
    figure_root,
    read_eval,
    write_json,
)
from sb3_hgrn.experiments.runs import evaluate_run
from sb3_hgrn.presets import HGAT_TWINS, PRESETS, TABLE1

FIGURES = {
    "ctc": "CTC learning curves: HGAT models against their homogeneous-attention twins",
    "alpha": "alpha, its gradient and the action entropy during Soft-HGRN and SAC-HGRN training on Surviving",
    "transfer": "team return per agent at other agent counts than the trained one, on Surviving",
    "p_alpha": "Soft-HGRN team return against the target-entropy ratio p_alpha, on Surviving",
}
"""Figure names and what they show."""

FIGURE_ENVS = {
    "ctc": "ctc_v0",
    "alpha": "surviving_v0",
    "transfer": "surviving_v0",
    "p_alpha": "surviving_v0",
}

DEFAULT_PRESETS = {
    "ctc": ("hgn", "dgn", "soft_hgrn", "soft_dgrn", "sac_hgrn", "sac_dgrn"),
    "alpha": ("soft_hgrn", "sac_hgrn"),
    "transfer": TABLE1,
    "p_alpha": ("soft_hgrn",),
}
TRANSFER_SCALES = (0.25, 0.5, 1.0, 2.0, 4.0)
"""Evaluation agent counts as multiples of the trained one (the paper: trained at 100, 25 to 400)."""
P_ALPHA_RATIOS = (0.05, 0.1, 0.2, 0.3, 0.5)
ALPHA_SERIES = ("alpha", "alpha_grad", "entropy", "target_entropy")
"""TensorBoard scalars ``train/<name>`` of the alpha figure."""
SMOOTHING = 0.04
"""Learning curves: moving average over this fraction of a run's training episodes (at least 1)."""
TRANSFER_FILE = "transfer.json"
PRINT = partial(print, flush=True)
METHOD_COLORS = {"soft_hgrn": "C0", "sac_hgrn": "C3"}
ABLATION_STYLES = {"": ("-", "o"), "G": ("--", "s"), "R": (":", "^"), "S": ("-.", "v")}
BASELINE_COLORS = ("C1", "C2", "C4", "C5", "C6", "C7", "C8", "C9")
MAP_NOTE = (
    "map, resource points and episode length kept as trained (the observation encodes coordinates "
    "in ceil(log2(map size)) bits, so a policy does not move to a map of another bit width); "
    "food regrowth scales with the agent count (threshold 2 n + 4)"
)


def check_figure_name(name: str) -> None:
    """Raise :class:`ConfigError` unless ``name`` is one of :data:`FIGURES`."""
    if name not in FIGURES:
        raise ConfigError(f"Unknown figure {name!r}; available: {', '.join(FIGURES)}.")


def check_presets(name: str, presets: Sequence[str]) -> None:
    """Raise :class:`ConfigError` for unknown presets, and for presets without a learned alpha in the
    ``alpha`` and ``p_alpha`` figures."""
    for preset in presets:
        check_preset_name(preset)
        kwargs = PRESETS[preset][1]
        if name in ("alpha", "p_alpha") and not (
            kwargs.get("stochastic", True) and kwargs.get("learn_alpha", True)
        ):
            raise ConfigError(f"Figure {name!r} needs a preset with a learned alpha, not {preset!r}.")


def ratio_root(root: Path, ratio: float) -> Path:
    """Root of the ``p_alpha`` runs with target-entropy ratio ``ratio``."""
    return root / f"ratio_{ratio:g}"


def plan_figure(
    name: str, root: Path, presets: Sequence[str], seeds: Sequence[int], ratios: Sequence[float]
) -> list[Job]:
    """Every run of figure ``name``, seed by seed (a partial sweep covers the figure with its first seeds).

    ``alpha`` runs log every team episode (``--log-interval 1``); ``p_alpha`` runs get
    ``--param target_entropy_ratio=R`` and their own root per ratio.
    """
    env = FIGURE_ENVS[name]
    if name == "p_alpha":
        return [
            replace(job, args=("--param", f"target_entropy_ratio={ratio:g}"))
            for seed in seeds
            for ratio in ratios
            for job in plan_jobs(ratio_root(root, ratio), [env], presets, [seed])
        ]
    args = ("--log-interval", "1") if name == "alpha" else ()
    return [replace(job, args=args) for job in plan_jobs(root, [env], presets, seeds)]


def figure_command_line(
    name: str,
    budget: str,
    n_seeds: int,
    folder: str | os.PathLike,
    jobs: int,
    out: Path,
    presets: Sequence[str],
    ratios: Sequence[float],
) -> str:
    """The ``sb3-hgrn figure`` command line that draws this figure."""
    words = ["sb3-hgrn", "figure", name, "--budget", budget, "--seeds", str(n_seeds)]
    words += ["--folder", str(folder), "--jobs", str(jobs), "--out", str(out)]
    if tuple(presets) != DEFAULT_PRESETS[name]:
        words += ["--presets", *presets]
    if name == "p_alpha" and tuple(ratios) != P_ALPHA_RATIOS:
        words += ["--ratios", *(f"{ratio:g}" for ratio in ratios)]
    return shlex.join(words)


def make_figure(
    name: str,
    budget: str = "cpu",
    n_seeds: int = 3,
    folder: str | os.PathLike = "results",
    jobs: int = 1,
    out: str | os.PathLike | None = None,
    presets: Sequence[str] | None = None,
    ratios: Sequence[float] | None = None,
    threads: int | None = None,
    save_freq: int | None = None,
    log: Callable[[str], None] = PRINT,
    backend: Backend | None = None,
) -> list[Job]:
    """Train the missing runs of figure ``name`` (``jobs`` processes at a time) and draw it.

    :param out: the PNG (default ``<folder>/figures/<name>.png``); ``.csv`` and ``.json`` go beside it.
    :param presets: methods drawn (default :data:`DEFAULT_PRESETS`).
    :param ratios: ``p_alpha`` only: target-entropy ratios (default :data:`P_ALPHA_RATIOS`).
    :param threads: torch threads per process (default: the backend's, for the local one 1 when
        ``jobs > 1``, else torch's own).
    :param save_freq: checkpoint every this many agent-steps, so that a killed run resumes.
    :param backend: where the runs execute (default: local processes).
    :return: the runs that failed (the figure is drawn from the others).
    """
    start = time.time()
    presets, ratios = check_arguments(name, budget, presets, ratios, n_seeds, jobs)
    backend = backend or LocalBackend()
    threads = backend.default_threads(jobs) if threads is None else threads
    out = Path(out) if out is not None else Path(folder) / "figures" / f"{name}.png"
    all_jobs = plan_figure(name, figure_root(folder, name), presets, list(range(n_seeds)), ratios)
    failed = train_missing(name, budget, all_jobs, jobs, threads, save_freq, log, backend)
    done = [job for job in all_jobs if read_eval(job.folder) is not None]
    if not done:
        log(f"No finished run to draw figure {name} from.")
        return failed
    rows, figure = draw_figure(name, done, threads, log)
    info = figure_info(name, budget, done, len(all_jobs), presets, n_seeds)
    info["command"] = figure_command_line(name, budget, n_seeds, folder, jobs, out, presets, ratios)
    if name == "p_alpha":
        info["ratios"] = ratios
    if name == "transfer":
        info["agent_counts"] = sorted({row["n_agents"] for row in rows})
        info["transfer_note"] = MAP_NOTE
    figure.text(0.5, 0.0, budget_note(info), ha="center", va="top", fontsize=8, wrap=True)
    info["wall_time_s"] = round(time.time() - start, 1)
    save_figure(figure, rows, info, out)
    log(summary(info, out))
    return failed


def check_arguments(
    name: str,
    budget: str,
    presets: Sequence[str] | None,
    ratios: Sequence[float] | None,
    n_seeds: int,
    jobs: int,
) -> tuple[list[str], list[float]]:
    """Check :func:`make_figure`'s arguments; returns the presets and ratios with their defaults."""
    check_figure_name(name)
    check_budget_name(budget)
    presets = list(presets or DEFAULT_PRESETS[name])
    check_presets(name, presets)
    if ratios is not None and name != "p_alpha":
        raise ConfigError("--ratios applies to the p_alpha figure only.")
    ratios = list(P_ALPHA_RATIOS if ratios is None else ratios)
    if not ratios or not all(0.0 <= ratio <= 1.0 for ratio in ratios):
        raise ConfigError(f"Target-entropy ratios must lie in [0, 1], got {ratios}.")
    if n_seeds < 1 or jobs < 1:
        raise ConfigError(f"--seeds and --jobs must be >= 1, got {n_seeds} and {jobs}.")
    return presets, ratios


def train_missing(
    name: str,
    budget: str,
    all_jobs: Sequence[Job],
    jobs: int,
    threads: int | None,
    save_freq: int | None,
    log: Callable[[str], None] = PRINT,
    backend: Backend | None = None,
) -> list[Job]:
    """Train every run of ``all_jobs`` without a complete ``eval.json``, ``jobs`` processes at a time
    on ``backend`` (runs of another budget in the same folders are refused); returns the runs that
    failed."""
    for root in dict.fromkeys(job.folder.parents[2] for job in all_jobs):
        check_budget_of_folder(root, budget)
    todo = [job for job in all_jobs if read_eval(job.folder) is None]
    log(
        f"Figure {name}, budget {budget}: {len(all_jobs)} runs, {len(all_jobs) - len(todo)} already done, "
        f"{len(todo)} to run, {jobs} at a time ({(backend or LocalBackend()).name} backend)"
    )
    return run_jobs(
        todo,
        lambda job: train_args(job, budget, job.folder.parents[2], threads, save_freq),
        jobs,
        threads,
        log,
        backend=backend,
    )


def draw_figure(
    name: str, done: Sequence[Job], threads: int | None = None, log: Callable[[str], None] = PRINT
) -> tuple[list[dict[str, Any]], Figure]:
    """Figure ``name`` drawn from the finished runs ``done`` (for ``transfer`` evaluated at the other
    agent counts first, with ``threads`` torch threads): ``(plotted rows, figure)``."""
    if name == "transfer":
        if threads is not None:
            import torch

            torch.set_num_threads(threads)
        evaluate_transfers(done, log)
    return DRAWERS[name](done)


def budget_note(info: dict[str, Any]) -> str:
    """One line under a figure: budget, env sizes, agent-steps per run and seeds."""
    return (
        f"budget {info['budget']}: {ENV_TITLES.get(info['env'], info['env'])}, {info['description']}; "
        f"{info['agent_steps']:,} agent-steps per run; seeds {_seed_list(info)}"
    )


def figure_info(
    name: str, budget: str, done: Sequence[Job], planned: int, presets: Sequence[str], n_seeds: int
) -> dict[str, Any]:
    """What a figure was drawn from: budget, env sizes, agent-steps, seeds, runs and their wall time."""
    env = FIGURE_ENVS[name]
    section = load_hyperparams(env)["budgets"][budget]
    evals = [read_eval(job.folder) or {} for job in done]
    return {
        "figure": name,
        "title": FIGURES[name],
        "budget": budget,
        "env": env,
        "description": section.get("description", ""),
        "n_agents": evals[0]["n_agents"],
        "n_envs": section["n_envs"],
        "agent_steps": evals[0]["agent_steps"],
        "env_steps": evals[0]["env_steps"],
        "eval_episodes": evals[0]["n_episodes"],
        "presets": list(presets),
        "seeds": n_seeds,
        "seeds_done": sorted({job.seed for job in done}),
        "runs_planned": planned,
        "runs_done": len(done),
        "runs_wall_time_s": round(sum(e["wall_time_s"] for e in evals), 1),
    }


def summary(info: dict[str, Any], out: Path) -> str:
    """What ``make_figure`` prints: files, command, budget, seeds and wall time."""
    copies = f"{info['n_envs']} env cop{'y' if info['n_envs'] == 1 else 'ies'}"
    return "\n".join(
        [
            f"Wrote {out}, {out.with_suffix('.csv')} and {out.with_suffix('.json')}",
            f"command: {info['command']}",
            f"budget {info['budget']}: {info['env']}, {info['description']}, {copies}; "
            f"{info['agent_steps']:,} agent-steps ({info['env_steps']:,} env steps) per run",
            f"seeds: {info['seeds']} planned, done: {_seed_list(info)}; "
            f"runs: {info['runs_done']} of {info['runs_planned']}",
            f"wall time: {info['wall_time_s']:.0f} s for this command, "
            f"{info['runs_wall_time_s']:.0f} s summed over the runs' training and evaluation",
        ]
    )


def _seed_list(info: dict[str, Any]) -> str:
    return ", ".join(map(str, info["seeds_done"]))


def save_figure(figure: Figure, rows: list[dict[str, Any]], info: dict[str, Any], out: Path) -> None:
    """Write the PNG, its plotted numbers (``.csv``) and what produced them (``.json``)."""
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(out, "wb") as file:
        figure.savefig(file, format="png", dpi=110, bbox_inches="tight")
    write_csv_atomically(
        out.with_suffix(".csv"), [{key: _round(value) for key, value in row.items()} for row in rows]
    )
    write_json(out.with_suffix(".json"), {**info, "png": str(out), "csv": str(out.with_suffix(".csv"))})


def _round(value: Any) -> Any:
    return float(f"{value:.6g}") if isinstance(value, float) else value


def _new_figure(width: float, height: float) -> Figure:
    figure = Figure(figsize=(width, height), layout="constrained")
    FigureCanvasAgg(figure)
    return figure


# --- curves over training -----------------------------------------------------------------------


def read_team_returns(folder: Path) -> tuple[np.ndarray, np.ndarray]:
    """Agent-steps done when each training team episode ended, and its team return.

    The agent-steps of an episode's row are the env steps of all episodes up to it (summed over env
    copies) times the agent count, from the run's ``team_returns.csv``.
    """
    lines = (folder / TEAM_RETURNS_FILE).read_text(encoding="utf-8").splitlines()
    n_agents = json.loads(lines[0][1:])["n_agents"]
    rows = list(csv.DictReader(lines[1:]))
    returns = np.array([float(row["r"]) for row in rows])
    lengths = np.array([int(row["l"]) for row in rows])
    return np.cumsum(lengths) * n_agents, returns


def moving_average(values: np.ndarray, window: int) -> np.ndarray:
    """Trailing mean of the last ``window`` values at every index (fewer at the start)."""
    sums = np.concatenate([[0.0], np.cumsum(values)])
    ends = np.arange(1, len(values) + 1)
    starts = np.maximum(0, ends - window)
    return (sums[ends] - sums[starts]) / (ends - starts)


def mean_band(curves: Sequence[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean and (population) std over curves ``(x, y)`` interpolated on a common grid of x.

    The grid spans the x range all curves cover, with as many points as the longest curve.
    """
    low, high = max(x[0] for x, _ in curves), min(x[-1] for x, _ in curves)
    grid = np.linspace(low, high, max(len(x) for x, _ in curves)) if high > low else np.array([high])
    values = np.stack([np.interp(grid, x, y) for x, y in curves])
    return grid, values.mean(axis=0), values.std(axis=0)


def _by_preset(done: Sequence[Job]) -> dict[str, list[Job]]:
    groups: dict[str, list[Job]] = {}
    for job in done:
        groups.setdefault(job.preset, []).append(job)
    return groups


def _curve_rows(
    preset: str, series: str, curves: list[tuple[np.ndarray, np.ndarray]]
) -> list[dict[str, Any]]:
    grid, mean, std = mean_band(curves)
    return [
        {
            "preset": preset,
            "series": series,
            "agent_steps": round(float(x)),
            "mean": float(m),
            "std": float(s),
            "n_seeds": len(curves),
        }
        for x, m, s in zip(grid, mean, std, strict=True)
    ]


def _plot_band(axis: Axes, rows: list[dict[str, Any]], label: str, **style: Any) -> None:
    x = np.array([row["agent_steps"] for row in rows])
    mean = np.array([row["mean"] for row in rows])
    std = np.array([row["std"] for row in rows])
    (line,) = axis.plot(x, mean, label=label, **style)
    axis.fill_between(x, mean - std, mean + std, color=line.get_color(), alpha=0.15, lw=0)


def _seeds_label(preset: str, n_seeds: int) -> str:
    return f"{PRESET_TITLES.get(preset, preset)} ({n_seeds} seed{'s' if n_seeds > 1 else ''})"


def draw_ctc(done: Sequence[Job]) -> tuple[list[dict[str, Any]], Figure]:
    """CTC learning curves: smoothed training team return against agent-steps, mean and std over
    seeds; HGAT models solid, their homogeneous-attention twins dashed in the same colour."""
    rows: list[dict[str, Any]] = []
    figure = _new_figure(8, 5)
    axis = figure.add_subplot()
    colors: dict[str, str] = {}
    windows = set()
    for preset, jobs in _by_preset(done).items():
        curves = []
        for job in jobs:
            steps, returns = read_team_returns(job.folder)
            window = max(1, round(SMOOTHING * len(returns)))
            windows.add(window)
            curves.append((steps, moving_average(returns, window)))
        preset_rows = _curve_rows(preset, "team_return", curves)
        rows += preset_rows
        family = HGAT_TWINS.get(preset, preset)
        colors.setdefault(family, f"C{len(colors)}")
        dashed = preset in HGAT_TWINS
        _plot_band(
            axis,
            preset_rows,
            _seeds_label(preset, len(jobs)),
            color=colors[family],
            ls="--" if dashed else "-",
        )
    axis.set_xlabel("agent-steps of training (all agents of all env copies)")
    axis.set_ylabel(f"training team return per episode\n({_smoothing(windows)})")
    axis.set_title(
        "CTC: HGAT models (solid) against their homogeneous-attention twins (dashed)\n"
        "mean over seeds, shaded: +- 1 std over seeds",
        fontsize=10,
    )
    axis.grid(alpha=0.3)
    axis.legend(fontsize=8)
    return rows, figure


def _smoothing(windows: set[int]) -> str:
    if windows == {1}:
        return "not smoothed"
    width = str(min(windows)) if len(windows) == 1 else f"{min(windows)}-{max(windows)}"
    return f"moving average of {width} episodes"


def read_scalars(
    folder: Path, tags: Sequence[str], optional: Sequence[str] = ()
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """TensorBoard scalars ``tag -> (steps, values)`` of a run (all its ``tensorboard/*`` logs); the
    ``optional`` tags are left out where the run does not log them."""
    try:
        from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
    except ImportError as error:
        raise ConfigError("Reading TensorBoard logs needs tensorboard (pip install tensorboard).") from error
    values: dict[str, dict[int, float]] = {tag: {} for tag in (*tags, *optional)}
    for log_dir in sorted((folder / TENSORBOARD_DIR).glob("*")):
        accumulator = EventAccumulator(str(log_dir), size_guidance={"scalars": 0})
        accumulator.Reload()
        available = set(accumulator.Tags()["scalars"])
        for tag in values:
            if tag in available:
                values[tag].update((event.step, event.value) for event in accumulator.Scalars(tag))
    missing = [tag for tag in tags if not values[tag]]
    if missing:
        raise ConfigError(
            f"{folder / TENSORBOARD_DIR} logs no {', '.join(missing)} (trained without tensorboard?)."
        )
    return {
        tag: (np.array(sorted(v)), np.array([v[step] for step in sorted(v)]))
        for tag, v in values.items()
        if v
    }


def draw_alpha(done: Sequence[Job]) -> tuple[list[dict[str, Any]], Figure]:
    """alpha, alpha's gradient and the action entropy against its target per logged step (mean and
    std over seeds)."""
    rows: list[dict[str, Any]] = []
    figure = _new_figure(8, 9)
    axes = figure.subplots(3, 1, sharex=True)
    for index, (preset, jobs) in enumerate(_by_preset(done).items()):
        scalars = [read_scalars(job.folder, [f"train/{name}" for name in ALPHA_SERIES]) for job in jobs]
        series = {
            name: _curve_rows(preset, name, [s[f"train/{name}"] for s in scalars]) for name in ALPHA_SERIES
        }
        rows += [row for name in ALPHA_SERIES for row in series[name]]
        label, color = _seeds_label(preset, len(jobs)), f"C{index}"
        _plot_band(axes[0], series["alpha"], label, color=color)
        _plot_band(axes[1], series["alpha_grad"], label, color=color)
        _plot_band(axes[2], series["entropy"], f"{label}: entropy", color=color)
        _plot_band(axes[2], series["target_entropy"], f"{label}: target", color=color, ls="--")
    axes[0].set_yscale("log")
    axes[0].set_ylabel("alpha (log scale)")
    axes[0].set_title("temperature alpha", fontsize=10)
    axes[1].axhline(0.0, color="grey", lw=1)
    axes[1].set_ylabel("gradient (nats)")
    axes[1].set_title(
        "alpha's gradient H - H_target (each update moves alpha by at most alpha_max_step)", fontsize=10
    )
    axes[2].set_ylabel("entropy (nats)")
    axes[2].set_title(
        "mean entropy H of softmax(Q / alpha) on the training batches and its target H_target",
        fontsize=10,
    )
    axes[2].set_xlabel("agent-steps of training (all agents of all env copies)")
    for axis in axes:
        axis.grid(alpha=0.3)
        axis.legend(fontsize=8)
    figure.suptitle(
        "Learned temperature during training on Surviving\n"
        "(values at each log dump; mean over seeds, shaded: +- 1 std)",
        fontsize=11,
    )
    return rows, figure


# --- evaluations of trained runs ----------------------------------------------------------------


def transfer_counts(trained: int, scales: Sequence[float] = TRANSFER_SCALES) -> list[int]:
    """Evaluation agent counts: ``scales`` times the trained count, rounded, at least 2."""
    return sorted({max(2, round(scale * trained)) for scale in scales})


def evaluate_transfer(folder: Path, counts: Sequence[int], n_episodes: int) -> dict[int, dict[str, Any]]:
    """Evaluate a finished run at every agent count of ``counts`` on its own map (env ``n_agents``).

    Results are kept in the run's ``transfer.json`` keyed by agent count, so a count already evaluated
    with ``n_episodes`` episodes of the same ``model.zip`` is not evaluated again.
    """
    path = folder / TRANSFER_FILE
    model_time = (folder / MODEL_FILE).stat().st_mtime_ns
    try:
        cache = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        cache = {}
    if cache.get("model_mtime_ns") != model_time:
        cache = {"model_mtime_ns": model_time, "counts": {}}
    for count in counts:
        if cache["counts"].get(str(count), {}).get("n_episodes") == n_episodes:
            continue
        start = time.time()
        result = evaluate_run(folder, n_episodes=n_episodes, n_agents=count)
        cache["counts"][str(count)] = {
            **result,
            "n_agents": count,
            "eval_time_s": round(time.time() - start, 2),
        }
        write_json(path, cache)
    return {count: cache["counts"][str(count)] for count in counts}


def evaluate_transfers(done: Sequence[Job], log: Callable[[str], None] = PRINT) -> None:
    """Evaluate every finished run at the transfer agent counts (the budget's evaluation episodes)."""
    for index, job in enumerate(done, 1):
        result = read_eval(job.folder) or {}
        counts = transfer_counts(result["n_agents"])
        start = time.time()
        evaluate_transfer(job.folder, counts, result["n_episodes"])
        log(
            f"[transfer {index}/{len(done)}] {job.label()}: evaluated (or reused) at {counts} agents "
            f"({time.time() - start:.0f} s)"
        )


def preset_style(preset: str, index: int) -> dict[str, Any]:
    """Colour, line and marker of a preset: one colour per family of the paper's methods (Soft-HGRN
    blue, SAC-HGRN red) with a line and marker per ablation, another colour per baseline (by ``index``)."""
    method, _, ablation = preset.partition("-")
    if method in METHOD_COLORS:
        line, marker = ABLATION_STYLES[ablation]
        return {"color": METHOD_COLORS[method], "ls": line, "marker": marker}
    return {"color": BASELINE_COLORS[index % len(BASELINE_COLORS)], "ls": "-", "marker": "D"}


def draw_transfer(done: Sequence[Job]) -> tuple[list[dict[str, Any]], Figure]:
    """Team return per agent (mean and std over seeds) against the agent count, one line per preset."""
    rows: list[dict[str, Any]] = []
    figure = _new_figure(8, 5.5)
    axis = figure.add_subplot()
    trained = set()
    for index, (preset, jobs) in enumerate(_by_preset(done).items()):
        per_count: dict[int, list[float]] = {}
        for job in jobs:
            result = read_eval(job.folder) or {}
            trained.add(result["n_agents"])
            evaluations = evaluate_transfer(
                job.folder, transfer_counts(result["n_agents"]), result["n_episodes"]
            )
            for count, evaluation in evaluations.items():
                per_count.setdefault(count, []).append(evaluation["mean"] / count)
        counts = sorted(per_count)
        means = [float(np.mean(per_count[n])) for n in counts]
        stds = [float(np.std(per_count[n])) for n in counts]
        rows += [
            {
                "preset": preset,
                "n_agents": n,
                "trained_agents": max(trained),
                "return_per_agent": m,
                "std": s,
                "n_seeds": len(per_count[n]),
                "seed_values": " ".join(f"{v:.4g}" for v in per_count[n]),
            }
            for n, m, s in zip(counts, means, stds, strict=True)
        ]
        axis.errorbar(
            counts,
            means,
            yerr=stds,
            ms=4,
            capsize=3,
            label=_seeds_label(preset, len(jobs)),
            **preset_style(preset, index),
        )
    for count in trained:
        axis.axvline(count, color="grey", ls=":", lw=1)
    all_counts = sorted({row["n_agents"] for row in rows})
    axis.set_xscale("log", base=2)
    axis.set_xticks(all_counts, [str(n) for n in all_counts])
    axis.set_xlabel(
        f"number of agents at evaluation (trained with {', '.join(map(str, sorted(trained)))}: dotted line)"
    )
    axis.set_ylabel("team return per agent per episode\n(evaluation, mean over episodes)")
    axis.set_title(
        "Transfer on Surviving: trained at one agent count, evaluated at others on the same map\n"
        "mean over seeds, bars: +- 1 std over seeds",
        fontsize=10,
    )
    axis.grid(alpha=0.3)
    axis.legend(fontsize=7, ncol=2)
    return rows, figure


def _config_value(folder: Path, key: str) -> Any:
    """An algorithm argument of a run as resolved (``extra.algorithm_kwargs`` of its ``config.yml``)."""
    config = yaml.safe_load((folder / CONFIG_FILE).read_text(encoding="utf-8"))
    return config["extra"]["algorithm_kwargs"][key]


def draw_p_alpha(done: Sequence[Job]) -> tuple[list[dict[str, Any]], Figure]:
    """Evaluation team return (mean and std over seeds, seeds as dots) against the target-entropy ratio."""
    rows: list[dict[str, Any]] = []
    figure = _new_figure(7, 4.5)
    axis = figure.add_subplot()
    for index, (preset, jobs) in enumerate(_by_preset(done).items()):
        per_ratio: dict[float, list[float]] = {}
        for job in jobs:
            ratio = float(_config_value(job.folder, "target_entropy_ratio"))
            per_ratio.setdefault(ratio, []).append((read_eval(job.folder) or {})["mean"])
        ratios = sorted(per_ratio)
        means = [float(np.mean(per_ratio[r])) for r in ratios]
        stds = [float(np.std(per_ratio[r])) for r in ratios]
        rows += [
            {
                "preset": preset,
                "target_entropy_ratio": r,
                "mean": m,
                "std": s,
                "n_seeds": len(per_ratio[r]),
                "seed_means": " ".join(f"{v:.2f}" for v in per_ratio[r]),
            }
            for r, m, s in zip(ratios, means, stds, strict=True)
        ]
        color = f"C{index}"
        axis.errorbar(
            ratios,
            means,
            yerr=stds,
            marker="o",
            capsize=4,
            color=color,
            label=f"{_seeds_label(preset, max(map(len, per_ratio.values())))}: mean +- std",
        )
        for ratio in ratios:
            axis.plot([ratio] * len(per_ratio[ratio]), per_ratio[ratio], ".", color=color, alpha=0.4)
    axis.set_xticks(sorted({row["target_entropy_ratio"] for row in rows}))
    axis.set_xlabel("target-entropy ratio p_alpha (target entropy = p_alpha x log 5 nats)")
    axis.set_ylabel("team return per episode\n(evaluation, mean over episodes)")
    axis.set_title("Parameter analysis of p_alpha on Surviving (dots: single seeds)", fontsize=10)
    axis.grid(alpha=0.3)
    axis.legend(fontsize=8)
    return rows, figure


DRAWERS: dict[str, Callable[[Sequence[Job]], tuple[list[dict[str, Any]], Figure]]] = {
    "ctc": draw_ctc,
    "alpha": draw_alpha,
    "transfer": draw_transfer,
    "p_alpha": draw_p_alpha,
}
"""Figure name -> function drawing it from the finished runs: ``(plotted rows, figure)``."""
