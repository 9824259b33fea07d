"""One training run into one folder; evaluating and rendering saved runs.

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

import importlib
import inspect
import itertools
import json
import operator
import os
import pickle
import re
import shutil
import sys
import time
import warnings
from collections.abc import Collection
from dataclasses import replace
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import yaml
from stable_baselines3.common.callbacks import BaseCallback

from sb3_hgrn.common.buffers import GraphReplayBuffer
from sb3_hgrn.common.evaluation import RandomGraphPolicy, evaluate_graph_policy
from sb3_hgrn.common.files import (
    DamagedModelFileError,
    check_model_file,
    describe_saved_model,
    model_file_path,
    remove_temporary_files,
    save_model_atomically,
    saved_policy_module,
    write_text_atomically,
)
from sb3_hgrn.common.off_policy import GraphOffPolicyAlgorithm
from sb3_hgrn.common.safe_load import read_saved_pickle
from sb3_hgrn.common.vec_env import GraphVecEnv, make_graph_vec_env
from sb3_hgrn.experiments.callbacks import (
    TEAM_RETURNS_FILE,
    AtomicCheckpointCallback,
    TeamMonitorCallback,
    checkpoint_companion,
    rewind_team_returns,
)
from sb3_hgrn.experiments.config import (
    ConfigError,
    RunConfig,
    check_env_name,
    env_folder_name,
    is_env_spec,
    load_env_factory,
)
from sb3_hgrn.experiments.lock import RunLock
from sb3_hgrn.presets import PRESETS, make_model, merge, preset_kwargs

CONFIG_FILE = "config.yml"
MODEL_FILE = "model.zip"
EVAL_FILE = "eval.json"
CHECKPOINT_DIR = "checkpoints"
TENSORBOARD_DIR = "tensorboard"
EVAL_SEED_OFFSET = 1000
"""Evaluation envs are seeded with ``seed + 1000`` so they never repeat the training episodes."""


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
    stored, current = _stored_config(folder), _plain(config.to_dict())
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


def _tensorboard_dir(folder: Path, verbose: int) -> str | None:
    try:
        import tensorboard  # noqa: F401
    except ImportError:
        if verbose:
            print("tensorboard is not installed: no TensorBoard logs (pip install tensorboard).")
        return None
    return str(folder / TENSORBOARD_DIR)


def make_env(config: RunConfig, n_envs: int, seed: int | None, **env_kwargs: Any) -> GraphVecEnv:
    """The run's env (``config.env_kwargs`` updated with ``env_kwargs``) as a graph VecEnv; a user env
    ``MODULE:ATTR`` is imported (:func:`~sb3_hgrn.experiments.config.load_env_factory`).

    Bad env arguments raise :class:`ConfigError` with the env's own message.
    """
    kwargs = {**config.env_kwargs, **env_kwargs}
    env = load_env_factory(config.env) if is_env_spec(config.env) else config.env
    try:
        return make_graph_vec_env(env, n_envs=n_envs, seed=seed, env_kwargs=kwargs)
    except (TypeError, ValueError) as error:
        raise ConfigError(f"Cannot build {config.env} with env arguments {kwargs}: {error}") from error


def new_model(
    config: RunConfig, env: GraphVecEnv, verbose: int, tensorboard_log: str | None, device: str
) -> GraphOffPolicyAlgorithm:
    """A fresh model of ``config``; bad algorithm arguments raise :class:`ConfigError`."""
    try:
        return make_model(
            config.preset,
            env,
            paper=config.paper,
            seed=config.seed,
            verbose=verbose,
            tensorboard_log=tensorboard_log,
            device=device,
            **config.hyperparams,
        )
    except (TypeError, ValueError) as error:
        raise ConfigError(
            f"Cannot build preset {config.preset} with arguments {config.hyperparams}: {error}"
        ) from error


def replay_buffer_bytes(config: RunConfig) -> int:
    """Bytes the replay buffer of a run of ``config`` holds once full
    (:meth:`~sb3_hgrn.common.buffers.GraphReplayBuffer.expected_nbytes`), without allocating it: a model
    is built on one env copy, with a buffer of one batch, for the spaces and the recurrent-state width."""
    env = make_env(config, 1, config.seed)
    try:
        slots = config.n_envs * env.n_agents
        algorithm, kwargs = preset_kwargs(config.preset, paper=config.paper, n_envs=slots)
        kwargs = merge(kwargs, config.hyperparams)
        defaults = inspect.signature(algorithm.__init__).parameters
        buffer_size, batch_size = (
            kwargs.get(name, defaults[name].default) for name in ("buffer_size", "batch_size")
        )
        one_batch = {**config.hyperparams, "buffer_size": batch_size * env.n_agents}
        model = new_model(
            replace(config, hyperparams=one_batch), env, verbose=0, tensorboard_log=None, device="cpu"
        )
    finally:
        env.close()
    return GraphReplayBuffer.expected_nbytes(
        buffer_size,
        model.observation_space,
        model.action_space,
        slots,
        env.n_agents,
        model.policy.state_dim,
        model.hidden_dtype,
    )


def train_run(
    config: RunConfig,
    folder: str | os.PathLike,
    verbose: int = 1,
    progress_bar: bool = False,
    save_freq: int | None = None,
    device: str = "auto",
    log_interval: int = 10,
    overwrite: bool = False,
    save_replay_buffer: bool = False,
    trust_config: bool = False,
) -> dict[str, Any]:
    """Train ``config`` into ``folder``, save ``model.zip``, evaluate and write ``eval.json``.

    The env and the model are built first, so bad arguments fail before the folder is touched. Then
    :func:`prepare_run_folder` decides: a killed run of the same configuration resumes from its latest
    checkpoint (``team_returns.csv`` rewound to the checkpoint's episodes) with the replay buffer saved
    beside it, if any, else with an empty one, and with its training state (env copies, last
    observation, recurrent and random states), if any, else with the envs reset; with both the
    resumed run is bit-identical to an uninterrupted one. A run killed after saving ``model.zip``
    (during its final evaluation) is evaluated from that model, without training. A complete run or
    one of another configuration is refused unless ``overwrite``, which moves the old run aside
    (kept, never deleted).

    :param save_freq: save a checkpoint every this many agent-steps (``None``: no checkpoints).
    :param log_interval: team episodes between log dumps.
    :param save_replay_buffer: save the replay buffer beside every checkpoint.
    :param trust_config: trust the files of the run folder: a checkpoint, replay buffer or training
        state that only full unpickling can load is loaded so (it can run code); without it, such a
        file is skipped with a warning (a checkpoint zip: an error).
    :return: the contents of ``eval.json``.
    """
    folder = Path(folder)
    start, cpu_start = time.time(), time.process_time()
    env = make_env(config, config.n_envs, config.seed)
    tensorboard_log = _tensorboard_dir(folder, verbose)
    model = new_model(config, env, verbose, tensorboard_log, device)
    with RunLock(folder):
        begin = prepare_run_folder(folder, config, overwrite)
        checkpoint = begin.model_file
        remove_temporary_files(folder)  # of a killed write: the lock says that no other process writes
        if begin.moved_aside is not None and verbose:
            print(
                f"Moved the old run aside to {begin.moved_aside} (kept: remove it once you no longer need it)"
            )
        if checkpoint is not None:
            model = PRESETS[config.preset][0].load(
                checkpoint,
                env=env,
                device=device,
                trust_pickle=trust_config,
                tensorboard_log=tensorboard_log,
                verbose=verbose,
            )
        if begin.finished:
            if verbose:
                print(f"Evaluating the finished model {checkpoint} ({model.num_timesteps} agent-steps)")
        elif checkpoint is not None:
            _resume(folder, model, checkpoint, verbose, trust_config)
        config.extra = _run_figures(config, env, model)
        write_text_atomically(folder / CONFIG_FILE, yaml.safe_dump(config.to_dict(), sort_keys=False))

        if not begin.finished:
            remaining = max(0, config.total_timesteps - model.num_timesteps)
            model.learn(
                remaining,
                callback=_callbacks(
                    folder,
                    config,
                    env,
                    save_freq,
                    resumed=checkpoint is not None,
                    save_replay_buffer=save_replay_buffer,
                ),
                log_interval=log_interval,
                progress_bar=progress_bar,
                reset_num_timesteps=checkpoint is None,
            )
            # No model.zip is here to be replaced: a whole one was evaluated, a damaged one set aside.
            save_model_atomically(model, folder / MODEL_FILE)
        env.close()
        train_time, train_cpu_time = time.time() - start, time.process_time() - cpu_start
        results = _final_evaluation(config, model)
        n_agents = int(config.extra["n_agents"])
        results.update(
            env=config.env,
            preset=config.preset,
            budget=config.budget,
            seed=config.seed,
            agent_steps=int(model.num_timesteps),
            env_steps=int(model.num_timesteps // n_agents),
            n_agents=n_agents,
            train_time_s=round(train_time, 2),
            train_cpu_s=round(train_cpu_time, 2),  # CPU seconds of all threads: steadier on a busy machine
            eval_time_s=round(time.time() - start - train_time, 2),
            wall_time_s=round(time.time() - start, 2),
            resumed_from=None if checkpoint is None else checkpoint.name,
            completed=True,
        )
        write_json(folder / EVAL_FILE, results)
    return results


def _resume(
    folder: Path, model: GraphOffPolicyAlgorithm, checkpoint: Path, verbose: int, trust_pickle: bool
) -> None:
    """Bring the run back to ``checkpoint``, whose model is ``model``: ``team_returns.csv`` rewound to
    its episodes, its replay buffer and training state loaded where they are whole (and need no
    unpickling beyond the safe loader's unless ``trust_pickle``)."""
    rewind_team_returns(folder / TEAM_RETURNS_FILE, model._episode_num)
    replay = _load_replay_buffer(model, checkpoint_companion(checkpoint, "replay_buffer"), trust_pickle)
    exact = _load_training_state(model, checkpoint_companion(checkpoint, "training_state"), trust_pickle)
    if verbose:
        print(
            f"Resuming from {checkpoint} ({model.num_timesteps} agent-steps done, "
            f"{'its' if replay else 'an empty'} replay buffer, "
            f"{'its env state' if exact else 'the envs reset'})"
        )


def _load_replay_buffer(model: GraphOffPolicyAlgorithm, path: Path, trust_pickle: bool) -> bool:
    """Load the replay buffer at ``path`` into ``model``; whether it was loaded (one that is damaged,
    does not fit or needs ``trust_pickle`` is skipped with a warning, leaving the model's empty buffer)."""
    if not path.is_file():
        return False
    try:
        model.load_replay_buffer(path, trust_pickle=trust_pickle)
    except (pickle.UnpicklingError, EOFError, AttributeError, TypeError, ValueError) as error:
        warnings.warn(f"Skipping the replay buffer {path}, which cannot be loaded: {error}", stacklevel=2)
        return False
    return True


def _load_training_state(model: GraphOffPolicyAlgorithm, path: Path, trust_pickle: bool) -> bool:
    """Restore the training state at ``path`` (env copies, last observation, recurrent state, random
    states) into ``model``; whether it was restored (one that is damaged, does not fit or needs
    ``trust_pickle`` is skipped with a warning, and the envs reset when training starts)."""
    if not path.is_file():
        return False
    try:
        state = read_saved_pickle(path, "training state", trust_pickle=trust_pickle)
        model.set_training_state(state, trust_pickle)
    except (pickle.UnpicklingError, EOFError, AttributeError, KeyError, TypeError, ValueError) as error:
        warnings.warn(f"Skipping the training state {path}, which cannot be loaded: {error}", stacklevel=2)
        return False
    return True


def _callbacks(
    folder: Path,
    config: RunConfig,
    env: GraphVecEnv,
    save_freq: int | None,
    resumed: bool,
    save_replay_buffer: bool,
) -> list[BaseCallback]:
    """The training callbacks of a run: ``team_returns.csv`` (continued when ``resumed``) and, with
    ``save_freq``, atomic checkpoints every ``save_freq`` agent-steps (with the replay buffer when
    ``save_replay_buffer``), the newest ``config.keep_checkpoints`` of them kept."""
    callbacks: list[BaseCallback] = [
        TeamMonitorCallback(str(folder / TEAM_RETURNS_FILE), env_id=config.env, append=resumed)
    ]
    if save_freq:
        callbacks.append(
            AtomicCheckpointCallback(
                max(1, save_freq // env.num_envs),
                str(folder / CHECKPOINT_DIR),
                name_prefix="model",
                save_replay_buffer=save_replay_buffer,
                keep=config.keep_checkpoints,
            )
        )
    return callbacks


def _final_evaluation(config: RunConfig, model: GraphOffPolicyAlgorithm) -> dict[str, Any]:
    """The trained model's evaluation on fresh env copies (seed ``seed + 1000``): the plain policy,
    then each of the budget's ``eval_epsilons`` under ``epsilon_evaluations``."""
    eval_env = make_env(config, config.eval_n_envs, config.seed + EVAL_SEED_OFFSET)
    try:
        results = evaluate_model(model, eval_env, config.eval_episodes, deterministic=False)
        for epsilon in config.eval_epsilons:
            eval_env.seed(config.seed + EVAL_SEED_OFFSET)
            eps_policy = EpsilonRandomPolicy(model, epsilon, seed=config.seed)
            eps_results = evaluate_model(eps_policy, eval_env, config.eval_episodes, deterministic=False)
            results.setdefault("epsilon_evaluations", {})[f"{epsilon:g}"] = eps_results
    finally:
        eval_env.close()
    return results


def evaluate_random_policy(config: RunConfig, folder: str | os.PathLike) -> dict[str, Any]:
    """Evaluate uniformly random valid actions on the evaluation envs of ``config`` (as a trained
    run's are: ``eval_n_envs`` copies seeded ``seed + 1000``, ``eval_episodes`` team episodes) and
    write ``folder/eval.json``; the anchor a table's learned policies are read against.

    :return: the contents of ``eval.json``.
    """
    folder = Path(folder)
    start = time.time()
    env = make_env(config, config.eval_n_envs, config.seed + EVAL_SEED_OFFSET)
    with RunLock(folder):
        try:
            results = evaluate_model(
                RandomGraphPolicy(env, seed=config.seed), env, config.eval_episodes, False
            )
            n_agents = int(env.n_agents)
        finally:
            env.close()
        results.update(
            env=config.env,
            preset=config.preset,
            budget=config.budget,
            seed=config.seed,
            agent_steps=0,
            env_steps=0,
            n_agents=n_agents,
            wall_time_s=round(time.time() - start, 2),
            completed=True,
        )
        write_json(folder / EVAL_FILE, results)
    return results


def _run_figures(config: RunConfig, env: GraphVecEnv, model: GraphOffPolicyAlgorithm) -> dict[str, Any]:
    """Figures of the set-up run recorded in ``config.yml``: class, resolved kwargs, sizes, versions."""
    import stable_baselines3
    import torch

    import sb3_hgrn

    algorithm, kwargs = preset_kwargs(config.preset, paper=config.paper, n_envs=env.num_envs)
    return {
        "algorithm": algorithm.__name__,
        "algorithm_kwargs": _plain(merge(kwargs, config.hyperparams)),
        "n_agents": int(env.n_agents),
        "num_envs": int(env.num_envs),
        "n_parameters": trained_parameter_count(model),
        "package_version": sb3_hgrn.__version__,
        "stable_baselines3_version": str(stable_baselines3.__version__),
        "torch_version": str(torch.__version__),
        "torch_threads": int(torch.get_num_threads()),
        "python": sys.version.split()[0],
        "command": " ".join(sys.argv),
    }


def trained_parameter_count(model: GraphOffPolicyAlgorithm) -> int:
    """The weights ``model``'s network optimisers train (the online Q-network, or the actor and the
    critics), each counted once; the target and averaged copies and the temperature are left out."""
    optimizers = [operator.attrgetter(name)(model) for name in model._optimizer_names()]
    params = {
        id(param): param
        for optimizer in optimizers
        for group in optimizer.param_groups
        for param in group["params"]
    }
    return int(sum(param.numel() for param in params.values()))


def _plain(value: Any) -> Any:
    """``value`` with tuples as lists and numpy scalars as Python numbers (for YAML and JSON)."""
    if isinstance(value, dict):
        return {key: _plain(item) for key, item in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(item) for item in value]
    if isinstance(value, np.generic):
        return value.item()
    return value


class PolicyWrapper:
    """Anything with a graph model's ``predict``, whose actions :meth:`adjust` sees (and may change).

    :param model: anything with a graph model's ``predict``.
    """

    def __init__(self, model: Any):
        self.model = model

    def predict(
        self,
        observation: dict[str, np.ndarray],
        state: Any = None,
        episode_start: Any = None,
        deterministic: bool = False,
    ) -> tuple[np.ndarray, Any]:
        """The wrapped model's actions ``(n_slots,)`` after :meth:`adjust`, and its state."""
        actions, state = self.model.predict(
            observation, state=state, episode_start=episode_start, deterministic=deterministic
        )
        return self.adjust(observation, np.asarray(actions)), state

    def adjust(self, observation: dict[str, np.ndarray], actions: np.ndarray) -> np.ndarray:
        """The actions to return instead of the model's ``actions`` ``(n_slots,)``."""
        raise NotImplementedError


class EpsilonRandomPolicy(PolicyWrapper):
    """A model whose action is replaced, per agent with probability ``epsilon``, by a uniformly random
    valid action (within ``obs["action_mask"]`` when present): the original code's evaluation mode.

    :param model: anything with a graph model's ``predict``.
    :param epsilon: probability of a random action per agent and step.
    """

    def __init__(self, model: Any, epsilon: float, seed: int | None = None):
        if not 0.0 <= epsilon <= 1.0:
            raise ValueError(f"epsilon must lie in [0, 1], got {epsilon}.")
        super().__init__(model)
        self.epsilon = epsilon
        self.n_actions = int(model.action_space.n)
        self.rng = np.random.default_rng(seed)

    def adjust(self, observation: dict[str, np.ndarray], actions: np.ndarray) -> np.ndarray:
        """Each action replaced by a random valid one with probability ``epsilon``."""
        n_slots = len(observation["obs"])
        mask = observation.get("action_mask")
        valid = (
            np.ones((n_slots, self.n_actions), dtype=bool) if mask is None else np.asarray(mask, dtype=bool)
        )
        random_actions = np.argmax(self.rng.random(valid.shape) * valid, axis=1)  # uniform among valid
        explore = self.rng.random(n_slots) < self.epsilon
        return np.where(explore, random_actions, actions)


class ActionCounter(PolicyWrapper):
    """A model whose actions are counted, per action index.

    :param model: anything with a graph model's ``predict``.
    :param n_actions: size of the (padded) action space.
    """

    def __init__(self, model: Any, n_actions: int):
        super().__init__(model)
        self.counts = np.zeros(n_actions, dtype=np.int64)

    def adjust(self, observation: dict[str, np.ndarray], actions: np.ndarray) -> np.ndarray:
        """The actions unchanged, counted."""
        self.counts += np.bincount(actions.ravel(), minlength=len(self.counts))
        return actions

    def frequencies(self) -> list[float]:
        """Fraction of all counted agent-steps that took each action (zeros before any step)."""
        return (self.counts / max(1, int(self.counts.sum()))).tolist()


def action_rule(model: Any, deterministic: bool) -> str:
    """How ``model.predict(..., deterministic=deterministic)`` picks its actions, before any
    :class:`PolicyWrapper` (such as :class:`EpsilonRandomPolicy`) changes them: ``"uniform random"``
    for a :class:`RandomGraphPolicy`, ``"greedy"`` with ``deterministic`` or for a graph model with
    ``stochastic=False`` (the DQN-style presets and the ``-S`` variants), ``"sampled"`` for a
    stochastic graph model, else ``"predict(deterministic=False)"`` (a model this cannot tell)."""
    while isinstance(model, PolicyWrapper):
        model = model.model
    if isinstance(model, RandomGraphPolicy):
        return "uniform random"
    stochastic = getattr(getattr(model, "policy", None), "stochastic", None)
    if deterministic or stochastic is False:
        return "greedy"
    return "sampled" if stochastic else "predict(deterministic=False)"


def evaluate_model(model: Any, env: GraphVecEnv, n_episodes: int, deterministic: bool) -> dict[str, Any]:
    """Team-return figures of ``n_episodes`` episodes: mean, std, per-episode returns and lengths, the
    fraction of agent-steps that took each action (over every step the evaluation ran), the action
    rule used (``actions``, see :func:`action_rule`; ``deterministic`` says whether it is greedy) and
    the probability ``epsilon`` of a random action mixed in."""
    counter = ActionCounter(model, int(env.action_space.n))
    returns, lengths = evaluate_graph_policy(
        counter, env, n_eval_episodes=n_episodes, deterministic=deterministic, return_episode_rewards=True
    )
    rule = action_rule(model, deterministic)
    return {
        "mean": float(np.mean(returns)),
        "std": float(np.std(returns)),
        "returns": [float(r) for r in returns],
        "lengths": [int(n) for n in lengths],
        "n_episodes": len(returns),
        "actions": rule,
        "deterministic": rule == "greedy",
        "epsilon": float(getattr(model, "epsilon", 0.0)),
        "action_frequencies": counter.frequencies(),
    }


def algorithm_of_zip(path: Path) -> type[GraphOffPolicyAlgorithm]:
    """``SoftHGRN`` or ``SACHGRN``, from the policy class recorded in a saved model."""
    import sb3_hgrn

    check_model_file(path)
    module = saved_policy_module(path)
    for name in ("sac_hgrn", "soft_hgrn"):
        if f"sb3_hgrn.{name}" in module:
            return getattr(sb3_hgrn, "SACHGRN" if name == "sac_hgrn" else "SoftHGRN")
    raise ConfigError(f"{path} is not an sb3_hgrn model: it was saved by {describe_saved_model(path)}.")


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


def check_stored_model_paths(
    config: RunConfig, folder: Path, given: Collection[str] = (), trust_config: bool = False
) -> None:
    """Raise :class:`ConfigError` when the ``config.yml`` of the run in ``folder`` makes its env load
    a saved model (e.g. a Pursuit controller) from outside the folder.

    Loading a model zip unpickles it and so can run code: a run's ``config.yml`` may only point to
    models inside its own folder, unless ``trust_config``. Env arguments in ``given`` (passed by the
    user, over the stored ones) are not checked. Which env arguments name models the env module says
    with ``model_paths(env_kwargs) -> {argument: path}`` (a registered env's module, or the module that
    defines a user env ``MODULE:ATTR``, imported here: call this after :func:`check_stored_env`).
    """
    if trust_config:
        return
    if is_env_spec(config.env):
        env_module = inspect.getmodule(load_env_factory(config.env))
    else:
        env_module = importlib.import_module(f"sb3_hgrn.envs.{config.env}")
    model_paths = getattr(env_module, "model_paths", None)
    if model_paths is None:
        return
    inside = folder.resolve()
    for name, value in model_paths(config.env_kwargs).items():
        if name not in given and not model_file_path(value).resolve().is_relative_to(inside):
            raise ConfigError(
                f"{folder / CONFIG_FILE} sets {name}={value!r}, a model outside the run folder. Loading a "
                "model file can run code, so a run's config may only name models inside its own folder. "
                f"If you trust this config, pass --trust-config (trust_config=True), or give the model "
                f"yourself with --env-param {name}=PATH."
            )


def check_stored_env(config: RunConfig, folder: Path, given: str | None, trust_config: bool = False) -> None:
    """Raise :class:`ConfigError` when the ``config.yml`` of the run in ``folder`` names a user env
    (``MODULE:ATTR``) that the user did not name too.

    Building a user env imports its module, which runs its code: a run's ``config.yml`` may name one
    only if the user gives the same with ``given`` (``--env``), or with ``trust_config``.
    """
    if trust_config or not is_env_spec(config.env) or given == config.env:
        return
    raise ConfigError(
        f"{folder / CONFIG_FILE} names the env {config.env!r}, code of its own that would be imported "
        "and run. A run's config may name such an env only if you name it too: pass "
        f"--env {config.env} (env={config.env!r}) if that is your env, or --trust-config "
        "(trust_config=True) if you trust this config."
    )


def load_run(
    path: str | os.PathLike,
    env: str | None = None,
    n_envs: int | None = None,
    seed: int | None = None,
    device: str = "auto",
    trust_config: bool = False,
    trust_pickle: bool = False,
    **env_kwargs: Any,
) -> tuple[GraphOffPolicyAlgorithm, GraphVecEnv, RunConfig]:
    """Load a saved run's model onto a fresh copy of its env (``env_kwargs`` over the run's).

    Models the run's ``config.yml`` names for its env are loaded only from inside the run folder
    unless ``trust_config`` (see :func:`check_stored_model_paths`), and a user env it names is
    imported only if ``env`` names it too or with ``trust_config`` (see :func:`check_stored_env`).
    The model zip is loaded without running code from it (see ``GraphOffPolicyAlgorithm.load``)
    unless ``trust_pickle`` or ``trust_config`` (trusting the run folder trusts its files).
    """
    model_path, config, folder = locate_run(path, env)
    if folder is not None:
        check_stored_env(config, folder, env, trust_config)
        check_stored_model_paths(config, folder, env_kwargs, trust_config)
    algorithm = PRESETS[config.preset][0] if config.preset in PRESETS else algorithm_of_zip(model_path)
    vec_env = make_env(
        config,
        n_envs or config.eval_n_envs,
        config.seed + EVAL_SEED_OFFSET if seed is None else seed,
        **env_kwargs,
    )
    model = algorithm.load(model_path, env=vec_env, device=device, trust_pickle=trust_pickle or trust_config)
    return model, vec_env, config


def evaluate_run(
    path: str | os.PathLike,
    n_episodes: int = 10,
    deterministic: bool = False,
    epsilon: float = 0.0,
    env: str | None = None,
    n_envs: int | None = None,
    seed: int | None = None,
    trust_config: bool = False,
    online: bool = False,
    trust_pickle: bool = False,
    **env_kwargs: Any,
) -> dict[str, Any]:
    """Evaluate a saved run (see :func:`load_run`); ``epsilon`` mixes in random valid actions;
    ``online`` acts with the online network (Q-network or actor) of a model that deploys a Polyak
    average (``policy_kwargs.average_tau``); ``trust_config``, ``trust_pickle``: see :func:`load_run`."""
    model, vec_env, _ = load_run(
        path,
        env=env,
        n_envs=n_envs,
        seed=seed,
        device="cpu",
        trust_config=trust_config,
        trust_pickle=trust_pickle,
        **env_kwargs,
    )
    if online:
        if model.policy.average_network is None:
            vec_env.close()
            raise ConfigError(
                f"{path}: --online needs a model that deploys an averaged network "
                "(trained with policy_kwargs.average_tau); this one acts with its online network already."
            )
        model.policy.drop_average()
    policy = EpsilonRandomPolicy(model, epsilon, seed=seed) if epsilon > 0 else model
    try:
        return evaluate_model(policy, vec_env, n_episodes, deterministic)
    finally:
        vec_env.close()


def render_run(
    path: str | os.PathLike,
    out: str | os.PathLike,
    steps: int | None = None,
    fps: float = 10.0,
    deterministic: bool = False,
    env: str | None = None,
    seed: int | None = None,
    trust_config: bool = False,
    trust_pickle: bool = False,
    **env_kwargs: Any,
) -> int:
    """Run one episode of copy 0 with ``render_mode="rgb_array"`` and write the frames as a GIF.

    :param steps: stop after this many steps (default: the whole episode).
    :param trust_config: see :func:`load_run`.
    :param trust_pickle: see :func:`load_run`.
    :return: the number of frames written.
    """
    from PIL import Image

    model, vec_env, _ = load_run(
        path,
        env=env,
        n_envs=1,
        seed=seed,
        device="cpu",
        render_mode="rgb_array",
        trust_config=trust_config,
        trust_pickle=trust_pickle,
        **env_kwargs,
    )
    try:
        observations = vec_env.reset()
        frames = [vec_env.render()]
        state, starts = None, np.ones(vec_env.num_envs, dtype=bool)
        step = 0
        while steps is None or step < steps:
            actions, state = model.predict(
                observations, state=state, episode_start=starts, deterministic=deterministic
            )
            observations, _, dones, _ = vec_env.step(actions)
            step += 1
            if dones[0]:  # the copy has already reset: its next frame would show a new episode
                break
            frames.append(vec_env.render())
    finally:
        vec_env.close()
    frames = [frame for frame in frames if frame is not None]
    if not frames:
        raise ConfigError(f"{vec_env} rendered no frames.")
    images = [Image.fromarray(np.asarray(frame, dtype=np.uint8)) for frame in frames]
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    images[0].save(out, save_all=True, append_images=images[1:], duration=max(1, round(1000 / fps)), loop=0)
    return len(images)
