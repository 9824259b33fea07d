"""A grid sweep: every combination of algorithm and env arguments, per preset and seed, on one env and
budget, trained by the job loop of the Table 1 sweep (:func:`sb3_hgrn.experiments.table1.run_jobs`).

A grid point is one value for every grid key, e.g. ``learning_rate=0.001`` and ``env.n_agents=10``
(env arguments carry the prefix ``env.``). Its runs go to
``<folder>/<point>/<env>/<preset>/seed_<seed>/``, where ``<point>`` names the values
(``learning_rate=0.001,env.n_agents=10``; ``default`` for a grid without keys), each trained as
``sb3-hgrn train ... --folder <folder>/<point> --param learning_rate=0.001 --env-param n_agents=10``.
Finished runs are skipped, so a stopped sweep continues where it stood and a grid can grow.
``<folder>/sweep.yml`` records the settings every point shares (env, budget, agent-steps, fixed
``--param`` / ``--env-param``, ``--config`` files): a folder is refused to a sweep with other shared
settings. After every
finished run ``<folder>/sweep.csv`` and ``<folder>/sweep.md`` are rewritten (mean +- std over seeds);
when the sweep ends they get the IQM with its 95 % stratified-bootstrap interval too
(:mod:`sb3_hgrn.experiments.stats`).

A grid file (``--grid-file``) is a YAML mapping with any of these keys::

    presets: [soft_hgrn, sac_hgrn]
    seeds: 3                                  # seeds 0..2
    grid: {learning_rate: [0.001, 0.0003], policy_kwargs.hidden_dim: [32, 64]}
    env_grid: {n_agents: [10, 20]}
    params: {batch_size: 64}                  # the same for every point
    env_params: {map_size: 16}

Its string values are read as the command line reads values (so ``1e-3``, which YAML leaves a
string, is a number).
"""

from __future__ import annotations

import itertools
import json
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import yaml

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
    ConfigError,
    budget_settings,
    check_budget_name,
    parse_assignments,
    parse_value,
    resolve_config,
)
from sb3_hgrn.experiments.jobs import Job, run_jobs, train_args
from sb3_hgrn.experiments.run_folder import read_eval, run_folder
from sb3_hgrn.experiments.stats import BOOTSTRAP_REPS, rliable_modules
from sb3_hgrn.validation import is_integer

ENV_PREFIX = "env."
"""Prefix of env arguments among a point's keys (``env.n_agents``)."""
DEFAULT_POINT = "default"
SETTINGS_FILE = "sweep.yml"
SUMMARY_CSV = "sweep.csv"
SUMMARY_MD = "sweep.md"
GRID_FILE_KEYS = ("presets", "seeds", "grid", "env_grid", "params", "env_params")


def split_values(text: str) -> list[str]:
    """Split ``"1e-3,3e-4"`` at its commas, except those inside brackets or braces
    (``"[1,2],[3]"`` gives ``["[1,2]", "[3]"]``)."""
    parts, depth, start = [], 0, 0
    for index, char in enumerate(text):
        depth += (char in "[{(") - (char in "]})")
        if char == "," and depth == 0:
            parts.append(text[start:index])
            start = index + 1
    parts.append(text[start:])
    return [part.strip() for part in parts]


def parse_grid(items: Sequence[str], option: str = "--grid") -> dict[str, list[Any]]:
    """``["learning_rate=1e-3,3e-4"]`` gives ``{"learning_rate": [0.001, 0.0003]}`` (dotted keys kept)."""
    grid: dict[str, list[Any]] = {}
    for item in items:
        key, sep, text = item.partition("=")
        values = split_values(text)
        if not sep or not key.strip() or not all(values):
            raise ConfigError(
                f"Malformed {option} {item!r}: expected key=value,value,... "
                f"(e.g. {option} learning_rate=1e-3,3e-4)."
            )
        grid[key.strip()] = [parse_value(value) for value in values]
    return grid


def _read_value(value: Any) -> Any:
    """A grid file's value as the command line would read it (strings parsed, containers entered)."""
    if isinstance(value, str):
        return parse_value(value)
    if isinstance(value, list):
        return [_read_value(item) for item in value]
    if isinstance(value, dict):
        return {key: _read_value(item) for key, item in value.items()}
    return value


def _mapping(data: dict[str, Any], key: str, where: str) -> dict[str, Any]:
    value = data.get(key) or {}
    if not isinstance(value, dict):
        raise ConfigError(f"{where}: {key} must be a mapping, got {type(value).__name__}.")
    return {str(name): _read_value(item) for name, item in value.items()}


def read_grid_file(path: str | os.PathLike) -> dict[str, Any]:
    """Read and check a grid file (see the module's docstring): a dict of its keys, values parsed."""
    try:
        data = yaml.safe_load(Path(path).read_text(encoding="utf-8")) or {}
    except (OSError, yaml.YAMLError) as error:
        raise ConfigError(f"Cannot read the grid file {path}: {error}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path} must be a mapping of {', '.join(GRID_FILE_KEYS)}.")
    unknown = sorted(str(key) for key in data if key not in GRID_FILE_KEYS)
    if unknown:
        expected = ", ".join(GRID_FILE_KEYS)
        raise ConfigError(f"{path}: unknown key(s) {', '.join(unknown)}; expected {expected}.")
    result = {key: _mapping(data, key, str(path)) for key in ("grid", "env_grid", "params", "env_params")}
    for key, values in [*result["grid"].items(), *result["env_grid"].items()]:
        if not isinstance(values, list) or not values:
            raise ConfigError(f"{path}: grid key {key!r} needs a non-empty list of values.")
    presets = data.get("presets")
    if presets is not None:
        result["presets"] = [presets] if isinstance(presets, str) else [str(p) for p in presets]
    if data.get("seeds") is not None:
        if not is_integer(data["seeds"]) or data["seeds"] < 1:
            raise ConfigError(f"{path}: seeds must be a positive number of seeds, got {data['seeds']!r}.")
        result["seeds"] = data["seeds"]
    return result


def format_value(value: Any) -> str:
    """A value as a folder name shows it: floats exactly (``0.001``, ``1e-05``), containers as
    compact JSON, ``/`` replaced by ``_``."""
    text = repr(value) if isinstance(value, float) else value if isinstance(value, str) else None
    if text is None:
        text = json.dumps(value, separators=(",", ":"))
    return text.replace(os.sep, "_")


def assignments(pairs: Sequence[tuple[str, Any]]) -> list[str]:
    """``key=value`` items of ``--param`` / ``--env-param`` whose values
    :func:`~sb3_hgrn.experiments.config.parse_value` reads back as they are (JSON text)."""
    return [f"{key}={json.dumps(value)}" for key, value in pairs]


def _options(params: list[str], env_params: list[str]) -> list[str]:
    """``--param ITEMS --env-param ITEMS``, each option only when it has items."""
    return [*(["--param", *params] if params else []), *(["--env-param", *env_params] if env_params else [])]


@dataclass(frozen=True)
class Point:
    """One grid point: algorithm arguments ``params`` and env arguments ``env_params`` (dotted keys)."""

    params: tuple[tuple[str, Any], ...] = ()
    env_params: tuple[tuple[str, Any], ...] = ()

    def items(self) -> list[tuple[str, Any]]:
        """``(key, value)`` of every grid key, env arguments prefixed with :data:`ENV_PREFIX`."""
        return [*self.params, *((ENV_PREFIX + key, value) for key, value in self.env_params)]

    def name(self) -> str:
        """The point's folder name: ``key=value`` joined by commas, or :data:`DEFAULT_POINT`."""
        words = [f"{key}={format_value(value)}" for key, value in self.items()]
        return ",".join(words) or DEFAULT_POINT

    def train_args(self) -> list[str]:
        """``--param key=value ... --env-param key=value ...`` of the point."""
        return _options(assignments(self.params), assignments(self.env_params))


def grid_points(grid: Mapping[str, Sequence[Any]], env_grid: Mapping[str, Sequence[Any]]) -> list[Point]:
    """Every combination of the values of ``grid`` and ``env_grid``, the last key varying fastest;
    a :class:`ConfigError` when two points would share a folder name."""
    keys = [(False, key) for key in grid] + [(True, key) for key in env_grid]
    value_lists = [list(grid[key]) for key in grid] + [list(env_grid[key]) for key in env_grid]
    points = []
    for values in itertools.product(*value_lists):
        pairs = list(zip(keys, values, strict=True))
        points.append(
            Point(
                tuple((key, value) for (is_env, key), value in pairs if not is_env),
                tuple((key, value) for (is_env, key), value in pairs if is_env),
            )
        )
    names = [point.name() for point in points]
    for name in names:
        if names.count(name) > 1:
            raise ConfigError(f"The grid has the point {name} twice: give each key distinct values.")
    return points


@dataclass
class SweepSettings:
    """What every point of a sweep shares (written to ``<folder>/sweep.yml``); ``params`` and
    ``env_params`` as :func:`~sb3_hgrn.experiments.config.parse_assignments` gives them (nested),
    ``config`` the ``--config`` files (needed by a user env ``MODULE:ATTR``)."""

    env: str
    budget: str
    timesteps: int | None = None
    params: dict[str, Any] = field(default_factory=dict)
    env_params: dict[str, Any] = field(default_factory=dict)
    config: list[str] = field(default_factory=list)

    def train_args(self) -> list[str]:
        """``--timesteps``, ``--param``, ``--env-param`` and ``--config`` of the shared settings."""
        steps = [] if self.timesteps is None else ["--timesteps", str(self.timesteps)]
        items = assignments(list(self.params.items())), assignments(list(self.env_params.items()))
        config = ["--config", *self.config] if self.config else []
        return [*steps, *_options(*items), *config]

    def record(self) -> dict[str, Any]:
        """Plain data for ``sweep.yml`` (without ``config`` when there is none, as before it existed)."""
        data = asdict(self)
        if not self.config:
            del data["config"]
        return data


def check_settings(folder: Path, settings: SweepSettings) -> None:
    """Write ``settings`` to ``folder/sweep.yml``, or check them against those already there."""
    path = folder / SETTINGS_FILE
    recorded = settings.record()
    if path.exists():
        before = yaml.safe_load(path.read_text(encoding="utf-8"))
        if before != recorded:
            raise ConfigError(
                f"{folder} holds a sweep with other shared settings ({path}: {before}, not {recorded}): "
                "use another --folder."
            )
        return
    folder.mkdir(parents=True, exist_ok=True)
    write_text_atomically(path, yaml.safe_dump(recorded, sort_keys=False))


def plan_sweep(
    folder: Path,
    settings: SweepSettings,
    points: Sequence[Point],
    presets: Sequence[str],
    seeds: Sequence[int],
) -> list[Job]:
    """Every run, seed by seed, point by point (a partial sweep covers the grid with its first seeds).
    A point's ``--param`` items come after the shared ones, so they win where both set a key."""
    shared = settings.train_args()
    return [
        Job(
            settings.env,
            preset,
            seed,
            run_folder(folder / point.name(), settings.env, preset, seed),
            (*shared, *point.train_args()),
        )
        for seed in seeds
        for point in points
        for preset in presets
    ]


def check_points(settings: SweepSettings, points: Sequence[Point], presets: Sequence[str]) -> None:
    """Resolve the configuration of every point and preset, so that an argument a preset's algorithm
    does not take is refused before any training."""
    shared = assignments(list(settings.params.items()))
    for point in points:
        params = parse_assignments([*shared, *assignments(point.params)])
        for preset in presets:
            resolve_config(
                settings.env,
                preset,
                settings.budget,
                timesteps=settings.timesteps,
                params=params,
                config_file=settings.config,
            )


def summary_rows(
    folder: Path,
    settings: SweepSettings,
    points: Sequence[Point],
    presets: Sequence[str],
    seeds: Sequence[int],
    reps: int | None = None,
) -> list[dict[str, Any]]:
    """One row per point and preset from the finished runs: the grid values, the IQM with its
    interval (``reps`` bootstrap resamples; ``None``: left empty), mean +- std over seeds of the runs'
    scores (mean evaluation team return), seeds done, agent-steps and summed wall time."""
    rows = []
    for point in points:
        for preset in presets:
            folders = [run_folder(folder / point.name(), settings.env, preset, seed) for seed in seeds]
            evals = [e for e in map(read_eval, folders) if e]
            scores = [e["mean"] for e in evals]
            mean, std = mean_std(scores)
            rows.append(
                {
                    "point": point.name(),
                    "preset": preset,
                    **dict(point.items()),
                    **iqm_columns(scores, reps),
                    "mean": mean,
                    "std": std,
                    "seeds_done": len(evals),
                    "seeds": len(seeds),
                    "seed_means": " ".join(f"{score:.2f}" for score in scores),
                    "agent_steps": evals[0]["agent_steps"] if evals else None,
                    "wall_time_s": round(sum(e["wall_time_s"] for e in evals), 1) if evals else None,
                }
            )
    return rows


def summary_markdown(rows: Sequence[dict[str, Any]], settings: SweepSettings, final: bool) -> str:
    """The summary table with the shared settings above it."""
    section = budget_settings(settings.env, settings.budget, settings.config)
    steps = settings.timesteps or section["total_timesteps"]
    shared = [f"`{key}={value}`" for key, value in {**settings.params, **settings.env_params}.items()]
    lines = [
        f"# Sweep on `{settings.env}`, budget `{settings.budget}`",
        "",
        (f"{section['description']}; " if section.get("description") else "")
        + f"{steps:,} agent-steps per run"
        + (f"; every point with {', '.join(shared)}" if shared else "")
        + ". A run's score is its mean evaluation team return. **IQM [95 % CI]**: interquartile mean "
        "of the seeds' scores with its 95 % stratified-bootstrap interval (rliable, "
        f"{BOOTSTRAP_REPS:,} resamples; with fewer than 4 seeds it is the mean). **mean +- std**: over "
        "seeds. `-`: no run finished.",
        "",
        "| point | preset | IQM [95 % CI] | mean +- std | seeds done | wall time (s) |",
        "|---|---|---|---|---|---|",
    ]
    for row in rows:
        iqm = format_interval(row["iqm"], row["iqm_low"], row["iqm_high"], format_number)
        wall = "-" if row["wall_time_s"] is None else f"{row['wall_time_s']:.0f}"
        lines.append(
            f"| `{row['point']}` | {row['preset']} | {iqm} | {format_cell(row['mean'], row['std'])} "
            f"| {row['seeds_done']}/{row['seeds']} | {wall} |"
        )
    scored = [row for row in rows if row["iqm"] is not None]
    if scored:
        best = max(scored, key=lambda row: row["iqm"])
        lines += ["", f"Highest IQM: `{best['point']}` with {best['preset']}."]
    if not final:
        lines += ["", "The IQM and its interval are computed when the sweep ends."]
    return "\n".join([*lines, ""])


def write_summary(
    folder: Path,
    settings: SweepSettings,
    points: Sequence[Point],
    presets: Sequence[str],
    seeds: Sequence[int],
    reps: int | None = BOOTSTRAP_REPS,
) -> list[dict[str, Any]]:
    """Write ``sweep.csv`` and ``sweep.md`` into ``folder`` (IQM columns empty when ``reps`` is None)."""
    rows = summary_rows(folder, settings, points, presets, seeds, reps)
    write_csv_atomically(folder / SUMMARY_CSV, rounded(rows, 4))
    write_text_atomically(folder / SUMMARY_MD, summary_markdown(rows, settings, reps is not None))
    return rows


def run_grid(
    settings: SweepSettings,
    presets: Sequence[str],
    n_seeds: int = 3,
    grid: Mapping[str, Sequence[Any]] | None = None,
    env_grid: Mapping[str, Sequence[Any]] | None = None,
    folder: str | os.PathLike = "sweeps",
    jobs: int = 1,
    threads: int | None = None,
    save_freq: int | None = None,
    log: Callable[[str], None] = print,
    backend: Backend | None = None,
) -> list[Job]:
    """Train every missing run of the grid, ``jobs`` at a time on ``backend`` (default: local
    processes), and write the summary.

    :param settings: env, budget and the arguments every point shares.
    :param grid: algorithm arguments and their values (dotted keys, as ``--param`` takes them).
    :param env_grid: env arguments and their values.
    :param threads: torch threads per run (default: the backend's).
    :param save_freq: checkpoint every this many agent-steps, so that a killed run resumes.
    :return: the runs that failed.
    """
    check_budget_name(settings.budget)
    if not presets:
        raise ConfigError("A sweep needs at least one preset.")
    if n_seeds < 1 or jobs < 1:
        raise ConfigError(f"--seeds and --jobs must be >= 1, got {n_seeds} and {jobs}.")
    for key, values in [*(grid or {}).items(), *(env_grid or {}).items()]:
        if not values:
            raise ConfigError(f"The grid key {key!r} has no values.")
    points = grid_points(grid or {}, env_grid or {})
    check_points(settings, points, presets)
    rliable_modules()  # the summary's IQM needs it: fail before training, not after
    backend = backend or LocalBackend()
    threads = backend.default_threads(jobs) if threads is None else threads
    root, seeds = Path(folder), list(range(n_seeds))
    check_settings(root, settings)
    all_jobs = plan_sweep(root, settings, points, presets, seeds)
    todo = [job for job in all_jobs if read_eval(job.folder) is None]
    log(
        f"Sweep on {settings.env}, budget {settings.budget}: {len(points)} point(s) x {len(presets)} "
        f"preset(s) x {n_seeds} seed(s) = {len(all_jobs)} runs, {len(all_jobs) - len(todo)} already "
        f"done, {len(todo)} to run, {jobs} at a time ({backend.name} backend)"
    )
    failed = run_jobs(
        todo,
        lambda job: train_args(job, settings.budget, job.folder.parents[2], threads, save_freq),
        jobs,
        threads,
        log,
        on_finished=lambda: write_summary(root, settings, points, presets, seeds, reps=None),
        backend=backend,
    )
    write_summary(root, settings, points, presets, seeds)
    log(f"Wrote {root / SUMMARY_CSV} and {root / SUMMARY_MD}")
    return failed
