"""Training runs of the single-agent algorithms from their RL Zoo-style hyperparameter files.

``sb3_hgrn/hyperparams/<preset>.yml`` maps Gymnasium env ids to settings: ``n_timesteps`` (env
steps), ``policy``, ``eval_episodes``, ``env_kwargs`` (keyword arguments of ``gymnasium.make``) and
the algorithm's own arguments. A run trains one seed into ``<folder>/<env>/<preset>/seed_<seed>``
(``model.zip``, ``eval.json``, TensorBoard logs under ``tb/``) and evaluates the greedy policy.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Sequence
from importlib import resources
from pathlib import Path
from typing import Any

import gymnasium as gym
import yaml
from stable_baselines3.common import torch_layers as sb3_torch_layers
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.monitor import Monitor

from sb3_hgrn.common import torch_layers
from sb3_hgrn.common.files import save_model_atomically, write_text_atomically
from sb3_hgrn.envs.registration import ensure_registered
from sb3_hgrn.experiments.config import ConfigError, read_yaml_file
from sb3_hgrn.presets import merge

SINGLE_AGENT_PRESETS = ("soft_dqn", "discrete_sac")
"""The presets that train single-agent Gymnasium envs, each with its ``hyperparams/<preset>.yml``."""

RUN_KEYS = ("n_timesteps", "policy", "eval_episodes", "env_kwargs")
"""Keys of an env's settings that are not arguments of the algorithm."""

EXTRACTORS = {
    "NatureCNN": sb3_torch_layers.NatureCNN,
    "FlattenExtractor": sb3_torch_layers.FlattenExtractor,
    "CombinedExtractor": sb3_torch_layers.CombinedExtractor,
    "AgentViewCNN": torch_layers.AgentViewCNN,
}
"""Features extractors a hyperparameter file may name in ``policy_kwargs.features_extractor_class``."""

DEFAULT_EVAL_EPISODES = 10


def is_single_agent_preset(preset: str) -> bool:
    """Whether ``preset`` trains single-agent envs (:data:`SINGLE_AGENT_PRESETS`)."""
    return preset in SINGLE_AGENT_PRESETS


def single_agent_run_folder(root: str | os.PathLike, env: str, preset: str, seed: int) -> Path:
    """``<root>/<env>/<preset>/seed_<seed>``, the env id's ``/`` and ``:`` written as ``-``
    (``minatar:MinAtar/Breakout-v1`` -> ``minatar-MinAtar-Breakout-v1``)."""
    return Path(root) / env.replace(":", "-").replace("/", "-") / preset / f"seed_{seed}"


def algorithm_class(preset: str) -> type[BaseAlgorithm]:
    """The algorithm class of a single-agent preset."""
    if preset == "soft_dqn":
        from sb3_hgrn.soft_dqn import SoftDQN

        return SoftDQN
    if preset == "discrete_sac":
        from sb3_hgrn.discrete_sac import DiscreteSAC

        return DiscreteSAC
    raise ConfigError(
        f"Unknown single-agent preset {preset!r}; available: {', '.join(SINGLE_AGENT_PRESETS)}."
    )


def read_hyperparams(preset: str, path: str | os.PathLike | None = None) -> dict[str, dict[str, Any]]:
    """The settings of every env in ``path`` (default: the packaged ``hyperparams/<preset>.yml``)."""
    if path is None:
        where = f"hyperparams/{preset}.yml"
        text = (resources.files("sb3_hgrn") / "hyperparams" / f"{preset}.yml").read_text(encoding="utf-8")
        table = yaml.safe_load(text)
    else:
        where = str(path)
        table = read_yaml_file(path, "hyperparameter file")
    if not isinstance(table, dict) or not all(isinstance(entry, dict) for entry in table.values()):
        raise ConfigError(f"The hyperparameter file {where} must map env ids to mappings of settings.")
    return table


def env_settings(
    preset: str,
    env: str,
    params: dict[str, Any] | None = None,
    config_files: Sequence[str | os.PathLike] = (),
) -> dict[str, Any]:
    """The settings of ``env`` for ``preset``: the packaged file's, those of ``config_files`` merged
    over them in order, then ``params`` (``policy_kwargs`` key by key), the features extractor named
    in ``policy_kwargs`` turned into its class."""
    where = " and ".join([f"hyperparams/{preset}.yml", *map(str, config_files)])
    tables = [read_hyperparams(preset), *(read_hyperparams(preset, path) for path in config_files)]
    if not any(env in table for table in tables):
        known = sorted({name for table in tables for name in table})
        raise ConfigError(f"{where} have no settings for the env {env!r}; they have: {', '.join(known)}.")
    settings: dict[str, Any] = {}
    for layer in [*(table.get(env, {}) for table in tables), params or {}]:
        settings = merge(settings, layer)
    n_timesteps = settings.get("n_timesteps")
    if not isinstance(n_timesteps, int | float) or isinstance(n_timesteps, bool) or n_timesteps < 1:
        raise ConfigError(
            f"{where}: {env}.n_timesteps must be a positive number of env steps, got {n_timesteps!r}."
        )
    policy_kwargs = dict(settings.get("policy_kwargs") or {})
    extractor = policy_kwargs.get("features_extractor_class")
    if isinstance(extractor, str):
        if extractor not in EXTRACTORS:
            raise ConfigError(
                f"{where}: {env}.policy_kwargs.features_extractor_class {extractor!r} is not one of "
                f"{', '.join(EXTRACTORS)}."
            )
        policy_kwargs["features_extractor_class"] = EXTRACTORS[extractor]
    return {**settings, "n_timesteps": int(n_timesteps), "policy_kwargs": policy_kwargs}


def make_model(
    preset: str,
    env: str,
    settings: dict[str, Any],
    seed: int,
    tensorboard_log: str | None = None,
    **kwargs: Any,
) -> BaseAlgorithm:
    """The model of ``preset`` on a fresh ``env`` (``gymnasium.make`` with the settings' ``env_kwargs``,
    in SB3's ``Monitor``) from its :func:`env_settings`; an argument the algorithm does not take
    raises a :class:`ConfigError` naming it."""
    arguments = {key: value for key, value in settings.items() if key not in RUN_KEYS}
    algorithm = algorithm_class(preset)
    try:
        return algorithm(
            settings.get("policy", "MlpPolicy"),
            Monitor(gym.make(ensure_registered(env), **settings.get("env_kwargs", {}))),
            seed=seed,
            tensorboard_log=tensorboard_log,
            **arguments,
            **kwargs,
        )
    except TypeError as error:
        raise ConfigError(
            f"Cannot build {algorithm.__name__} on {env} from {sorted(arguments)}: {error}"
        ) from error


def train_single_agent(
    preset: str,
    env: str,
    seed: int,
    folder: str | os.PathLike,
    timesteps: int | None = None,
    params: dict[str, Any] | None = None,
    config_files: Sequence[str | os.PathLike] = (),
    overwrite: bool = False,
    **kwargs: Any,
) -> dict[str, Any]:
    """Train ``preset`` on ``env`` for ``timesteps`` env steps (default: the settings'
    ``n_timesteps``) into ``folder``, evaluate its greedy policy on ``eval_episodes`` episodes of an
    env seeded ``seed + 1000`` and return (and write to ``eval.json``) the results.

    A folder that holds a finished run (``eval.json``) raises a :class:`ConfigError` unless
    ``overwrite``; files are written to a temporary name, then renamed. ``kwargs`` go to the
    algorithm (``verbose``, ``device``).
    """
    folder = Path(folder)
    if (folder / "eval.json").exists() and not overwrite:
        raise ConfigError(f"{folder} holds a finished run (eval.json); pass --overwrite to train it again.")
    settings = env_settings(preset, env, params, config_files)
    folder.mkdir(parents=True, exist_ok=True)
    model = make_model(preset, env, settings, seed, str(folder / "tb"), **kwargs)
    steps = timesteps or settings["n_timesteps"]
    start = time.perf_counter()
    model.learn(steps)
    wall_time = time.perf_counter() - start
    save_model_atomically(model, folder / "model.zip")
    eval_env = Monitor(gym.make(ensure_registered(env), **settings.get("env_kwargs", {})))
    eval_env.reset(seed=seed + 1000)
    episodes = int(settings.get("eval_episodes", DEFAULT_EVAL_EPISODES))
    mean, std = evaluate_policy(model, eval_env, n_eval_episodes=episodes, deterministic=True)
    results = {
        "env": env,
        "preset": preset,
        "seed": seed,
        "mean": float(mean),
        "std": float(std),
        "n_episodes": episodes,
        "env_steps": int(model.num_timesteps),
        "wall_time_s": wall_time,
    }
    write_text_atomically(folder / "eval.json", json.dumps(results, indent=2))
    return results
