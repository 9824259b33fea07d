"""The run folder: its layout, how a run starts in it, and finding a saved run's files.

A run folder (``<root>/<env>/<preset>/seed_<seed>/``, a user env ``MODULE:ATTR`` as ``MODULE-ATTR``)
holds::

    config.yml          the resolved configuration (env, env_kwargs, n_envs, preset, algorithm kwargs,
                        budget, seed, versions)
    tensorboard/        SB3's TensorBoard logs (when tensorboard is installed)
    team_returns.csv    one "r,l,t" row per training team episode, after a "#{json}" line (as SB3's Monitor)
    checkpoints/        model_<agent-steps>_steps.zip every --save-freq agent-steps (optional) with
                        model_training_state_<agent-steps>_steps.pkl (env copies, last observation,
                        recurrent and random states), with --save-replay-buffer also
                        model_replay_buffer_<agent-steps>_steps.pkl
    model.zip           the final model
    eval.json           the final evaluation; its presence marks the run as complete
    .lock, .lock.pid    the lock of the process working in the folder, and its pid

Every file but ``team_returns.csv`` (appended to row by row) is written atomically; the temporary
file of a write cut short by a kill is removed when a run starts in the folder again. No model is
ever deleted here: ``--overwrite`` moves an old run to ``<folder>.replaced-<UTC time>/``, which is
kept, a damaged model zip is renamed to ``<name>.damaged-<UTC time>.zip`` beside it, and a run killed
after saving ``model.zip`` but before writing ``eval.json`` is evaluated, not trained again.
"""

from __future__ import annotations

import itertools
import json
import os
import re
import shutil
import time
import warnings
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import yaml

from sb3_hgrn.common.files import (
    DamagedModelFileError,
    check_model_file,
    write_text_atomically,
)
from sb3_hgrn.experiments.callbacks import TEAM_RETURNS_FILE
from sb3_hgrn.experiments.config import (
    ConfigError,
    RunConfig,
    check_env_name,
    env_folder_name,
)

CONFIG_FILE = "config.yml"
MODEL_FILE = "model.zip"
EVAL_FILE = "eval.json"
CHECKPOINT_DIR = "checkpoints"
TENSORBOARD_DIR = "tensorboard"


def run_folder(root: str | os.PathLike, env: str, preset: str, seed: int) -> Path:
    """``<root>/<env>/<preset>/seed_<seed>``, ``<env>`` as :func:`env_folder_name` writes it."""
    return Path(root) / env_folder_name(env) / preset / f"seed_{seed}"


def figure_root(folder: str | os.PathLike, name: str) -> Path:
    """Where figure ``name`` keeps its runs: ``<folder>/figures/<name>``, except the transfer figure,
    whose runs are Table 1's Surviving runs (the same budget, presets and seeds) in ``<folder>/table1``,
    so ``reproduce table1`` and ``figure transfer`` share them."""
    return Path(folder) / "table1" if name == "transfer" else Path(folder) / "figures" / name


def read_eval(folder: str | os.PathLike) -> dict[str, Any] | None:
    """The run's ``eval.json`` if it is complete, else ``None``."""
    path = Path(folder) / EVAL_FILE
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) and data.get("completed") else None


def write_json(path: Path, data: dict[str, Any]) -> None:
    """Write ``data`` atomically (a killed process never leaves half a file)."""
    write_text_atomically(path, json.dumps(data, indent=2) + "\n")


def _checkpoints(folder: Path) -> list[Path]:
    """The checkpoints in ``folder/checkpoints``, most agent-steps first."""
    steps = {}
    for path in (folder / CHECKPOINT_DIR).glob("*_steps.zip"):
        match = re.search(r"_(\d+)_steps\.zip$", path.name)
        if match:
            steps[path] = int(match.group(1))
    return sorted(steps, key=steps.__getitem__, reverse=True)


def _first_good(paths: list[Path]) -> Path | None:
    """The first of ``paths`` that is a whole model zip; every damaged one before it is skipped with
    a warning."""
    for path in paths:
        try:
            check_model_file(path)
        except DamagedModelFileError as error:
            warnings.warn(f"Skipping {error}", stacklevel=3)
            continue
        return path
    return None


RUN_ENTRIES = (CONFIG_FILE, MODEL_FILE, EVAL_FILE, TEAM_RETURNS_FILE, CHECKPOINT_DIR, TENSORBOARD_DIR)
"""What a run writes into its folder (other files, e.g. a sweep's ``train.log``, are not the run's)."""
_MISSING = object()


UNCOMPARED_KEYS = ("extra", "keep_checkpoints")
"""Top-level keys of ``config.yml`` that may change when a run resumes: ``extra`` records versions
and the command line, ``keep_checkpoints`` how many checkpoints stay on disk; neither changes what the
run computes."""


def config_differences(stored: dict[str, Any], current: dict[str, Any], prefix: str = "") -> list[str]:
    """Dotted keys whose values differ between two configurations (the top-level
    :data:`UNCOMPARED_KEYS` are ignored)."""
    differences = []
    for key in dict.fromkeys([*stored, *current]):
        if not prefix and key in UNCOMPARED_KEYS:
            continue
        old, new = stored.get(key, _MISSING), current.get(key, _MISSING)
        if isinstance(old, dict) and isinstance(new, dict):
            differences += config_differences(old, new, f"{prefix}{key}.")
        elif old != new:
            differences.append(f"{prefix}{key}")
    return differences


def _describe_differences(stored: dict[str, Any], current: dict[str, Any], keys: list[str]) -> str:
    """``key (stored A, now B)`` for every differing dotted key."""

    def value(data: Any, key: str) -> str:
        for part in key.split("."):
            data = data.get(part, _MISSING)
        return "missing" if data is _MISSING else repr(data)

    return "; ".join(f"{key} (stored {value(stored, key)}, now {value(current, key)})" for key in keys)


def _stored_config(folder: Path) -> dict[str, Any] | None:
    """The folder's ``config.yml`` as a mapping, ``None`` if it is missing or unreadable."""
    try:
        data = yaml.safe_load((folder / CONFIG_FILE).read_text(encoding="utf-8"))
    except (OSError, yaml.YAMLError):
        return None
    return data if isinstance(data, dict) else None


def _has_run(folder: Path) -> bool:
    """Whether ``folder`` holds any file a run writes."""
    return any((folder / name).exists() for name in RUN_ENTRIES)


def _clear_logs(folder: Path) -> None:
    """Remove the logs of a run killed before it saved any model, which starts again from scratch:
    its ``config.yml``, ``eval.json``, ``team_returns.csv`` and ``tensorboard/``. Models (``model.zip``,
    ``checkpoints/``) are not touched; other files, e.g. a sweep's log, stay."""
    for name in (CONFIG_FILE, EVAL_FILE, TEAM_RETURNS_FILE):
        (folder / name).unlink(missing_ok=True)
    shutil.rmtree(folder / TENSORBOARD_DIR, ignore_errors=True)


def _aside_path(path: Path, label: str) -> Path:
    """A free name beside ``path``: ``<stem>.<label>-<UTC time>[-<i>]<suffix>``
    (``seed_0`` -> ``seed_0.replaced-20261201T161500Z``, ``model.zip`` -> ``model.damaged-...zip``)."""
    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
    names = (
        path.with_name(f"{path.stem}.{label}-{stamp}{f'-{index}' if index else ''}{path.suffix}")
        for index in itertools.count()
    )
    return next(aside for aside in names if not aside.exists())


def move_run_aside(folder: Path) -> Path | None:
    """Move the run files of ``folder`` into ``<folder>.replaced-<UTC time>/`` beside it (other files
    stay); returns that folder, ``None`` when there was nothing to move. The folder is kept."""
    if not _has_run(folder):
        return None
    aside = _aside_path(folder, "replaced")
    aside.mkdir(parents=True)
    for name in RUN_ENTRIES:
        if (folder / name).exists():
            os.rename(folder / name, aside / name)  # aside is new and empty: nothing is replaced
    return aside


def _set_damaged_aside(path: Path) -> None:
    """Rename the damaged model zip ``path`` to ``<stem>.damaged-<UTC time>.zip`` beside it, with a
    warning: kept for inspection, out of the way of the files a run writes."""
    aside = _aside_path(path, "damaged")
    os.rename(path, aside)
    warnings.warn(f"Renamed the damaged model file {path} to {aside.name}", stacklevel=3)


def _finished_model(folder: Path) -> Path | None:
    """The folder's ``model.zip`` if it is whole: a run that saved its final model (a damaged one is
    set aside, see :func:`_set_damaged_aside`)."""
    path = folder / MODEL_FILE
    if not path.is_file():
        return None
    try:
        check_model_file(path)
    except DamagedModelFileError:
        _set_damaged_aside(path)
        return None
    return path


def _resumable_checkpoint(folder: Path) -> Path | None:
    """The newest whole checkpoint of ``folder``; the damaged ones newer than it are set aside (see
    :func:`_set_damaged_aside`), so the resumed run never writes over them."""
    checkpoints = _checkpoints(folder)
    checkpoint = _first_good(checkpoints)
    for damaged in checkpoints[: checkpoints.index(checkpoint) if checkpoint else len(checkpoints)]:
        _set_damaged_aside(damaged)
    return checkpoint


class RunStart(NamedTuple):
    """How a run starts in its folder (see :func:`prepare_run_folder`)."""

    model_file: Path | None
    """The model to load (``None``: a fresh one): the checkpoint to resume, or the final model."""
    finished: bool
    """``model_file`` is the run's final ``model.zip``: the run is evaluated, not trained further."""
    moved_aside: Path | None
    """Where ``--overwrite`` moved the old run (kept), ``None`` if it did not."""


def prepare_run_folder(folder: Path, config: RunConfig, overwrite: bool) -> RunStart:
    """Decide how a run starts in ``folder``.

    With ``overwrite`` an old run is moved aside (:func:`move_run_aside`). Otherwise a complete run
    is refused, a run of another configuration is refused naming the differing keys, and a run of
    the same configuration goes on: with a whole ``model.zip`` (killed during its final evaluation)
    it is evaluated, else it resumes from its latest whole checkpoint, else (killed before its first)
    it starts again, its logs cleared. No model is deleted: damaged ones are renamed aside.
    """
    if overwrite:
        return RunStart(None, False, move_run_aside(folder))
    if read_eval(folder) is not None:
        raise ConfigError(
            f"{folder} already holds a completed run ({EVAL_FILE}); pass --overwrite to redo it "
            "(the old run is moved aside)."
        )
    if not _has_run(folder):
        return RunStart(None, False, None)
    stored, current = _stored_config(folder), plain(config.to_dict())
    if stored is None:
        raise ConfigError(
            f"{folder} holds a run without a readable {CONFIG_FILE}; pass --overwrite to replace it "
            "(the old run is moved aside)."
        )
    differences = config_differences(stored, current)
    if differences:
        raise ConfigError(
            f"{folder} holds a run of another configuration, refusing to resume it: "
            f"{_describe_differences(stored, current, differences)}. Pass --overwrite to replace it "
            "(the old run is moved aside), or use another --folder."
        )
    finished = _finished_model(folder)
    if finished is not None:
        return RunStart(finished, True, None)
    checkpoint = _resumable_checkpoint(folder)
    if checkpoint is None:
        _clear_logs(folder)
    return RunStart(checkpoint, False, None)


def plain(value: Any) -> Any:
    """``value`` with tuples as lists and numpy scalars as Python numbers (for YAML and JSON)."""
    if isinstance(value, dict):
        return {key: plain(item) for key, item in value.items()}
    if isinstance(value, list | tuple):
        return [plain(item) for item in value]
    if isinstance(value, np.generic):
        return value.item()
    return value


def locate_run(path: str | os.PathLike, env: str | None = None) -> tuple[Path, RunConfig, Path | None]:
    """The model file, run configuration and run folder (the one holding ``config.yml``, ``None``
    without one) of ``path`` (a run folder, its ``model.zip`` or a checkpoint).

    A run folder gives its ``model.zip``, else its latest checkpoint; damaged ones are skipped with a
    warning. A damaged file given by name raises :class:`ConfigError` ("damaged model file"). A bare
    ``.zip`` outside any run folder needs ``env`` (then the env's defaults are used).
    """
    path = Path(path)
    if path.is_dir():
        final = [path / MODEL_FILE] if (path / MODEL_FILE).exists() else []
        model_path = _first_good([*final, *_checkpoints(path)])
        if model_path is None:
            raise ConfigError(f"{path} holds neither a whole {MODEL_FILE} nor a whole checkpoint.")
        candidates = [path]
    else:
        if not path.exists() and Path(f"{path}.zip").exists():
            path = Path(f"{path}.zip")
        if not path.exists():
            raise ConfigError(f"No run folder or model file at {path}.")
        try:
            check_model_file(path)
        except DamagedModelFileError as error:
            raise ConfigError(str(error)) from error
        model_path = path
        candidates = [path.parent, path.parent.parent]
    for folder in candidates:
        if (folder / CONFIG_FILE).exists():
            data = yaml.safe_load((folder / CONFIG_FILE).read_text(encoding="utf-8"))
            config = RunConfig.from_dict(data)
            if env is not None and env != config.env:
                raise ConfigError(f"{path} was trained on {config.env}, not {env}.")
            return model_path, config, folder
    if env is None:
        raise ConfigError(f"No {CONFIG_FILE} beside {path}: pass --env to say which env it runs on.")
    check_env_name(env)
    return model_path, RunConfig(env, "", "", 0, {}, 1, 1, 0, 10, [], False, {}), None
