"""Training a run into its folder (see :mod:`sb3_hgrn.experiments.run_folder` for its files), loading
and evaluating saved runs."""

from __future__ import annotations

import inspect
import operator
import os
import pickle
import sys
import time
import warnings
from dataclasses import replace
from pathlib import Path
from typing import Any

import yaml
from stable_baselines3.common.callbacks import BaseCallback

from sb3_hgrn.common.buffers import GraphReplayBuffer
from sb3_hgrn.common.evaluation import RandomGraphPolicy
from sb3_hgrn.common.files import (
    check_model_file,
    describe_saved_model,
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
    is_env_spec,
    load_env_factory,
)
from sb3_hgrn.experiments.lock import RunLock
from sb3_hgrn.experiments.policy_evaluation import EpsilonRandomPolicy, evaluate_model
from sb3_hgrn.experiments.run_folder import (
    CHECKPOINT_DIR,
    CONFIG_FILE,
    EVAL_FILE,
    MODEL_FILE,
    TENSORBOARD_DIR,
    locate_run,
    plain,
    prepare_run_folder,
    write_json,
)
from sb3_hgrn.experiments.trust import check_stored_env, check_stored_model_paths
from sb3_hgrn.presets import PRESETS, make_model, merge, preset_kwargs

EVAL_SEED_OFFSET = 1000
"""Evaluation envs are seeded with ``seed + 1000`` so they never repeat the training episodes."""


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
        "algorithm_kwargs": plain(merge(kwargs, config.hyperparams)),
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


def algorithm_of_zip(path: Path) -> type[GraphOffPolicyAlgorithm]:
    """``SoftHGRN`` or ``SACHGRN``, from the policy class recorded in a saved model."""
    import sb3_hgrn

    check_model_file(path)
    module = saved_policy_module(path)
    for name in ("sac_hgrn", "soft_hgrn"):
        if f"sb3_hgrn.{name}" in module:
            return getattr(sb3_hgrn, "SACHGRN" if name == "sac_hgrn" else "SoftHGRN")
    raise ConfigError(f"{path} is not an sb3_hgrn model: it was saved by {describe_saved_model(path)}.")


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
    critic: bool = False,
    **env_kwargs: Any,
) -> dict[str, Any]:
    """Evaluate a saved run (see :func:`load_run`); ``epsilon`` mixes in random valid actions;
    ``online`` acts with the online network (Q-network, actor or acting critic) of a model that
    deploys a Polyak average (``policy_kwargs.average_tau``); ``critic`` acts with a SAC-HGRN model's
    online first critic's Boltzmann policy instead of what it deploys; ``trust_config``,
    ``trust_pickle``: see :func:`load_run`."""
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
    if critic:
        if online:
            vec_env.close()
            raise ConfigError(
                f"{path}: --critic and --online name two different networks to act with; give one."
            )
        if not hasattr(model.policy, "acts_with_critic"):
            vec_env.close()
            raise ConfigError(
                f"{path}: --critic needs an actor-critic model (SACHGRN); this {type(model).__name__} "
                "acts with its Q-network already."
            )
        model.policy.acts_with_critic = True
    policy = EpsilonRandomPolicy(model, epsilon, seed=seed) if epsilon > 0 else model
    try:
        return evaluate_model(policy, vec_env, n_episodes, deterministic)
    finally:
        vec_env.close()
