"""Gymnasium env ids of plugin packages: their namespaces registered on first use."""

from __future__ import annotations

from importlib.metadata import entry_points

import gymnasium as gym

PLUGIN_GROUP = "gymnasium.envs"
"""The entry-point group in which a package names the function that registers its envs (MinAtar's
``MinAtar = minatar.gym:register_envs``). Gymnasium 1.0 and later no longer call these themselves."""


def ensure_registered(env_id: str) -> str:
    """``env_id``, after registering its namespace's envs from the :data:`PLUGIN_GROUP` entry point
    of that name, where the id is not registered yet (``MinAtar/Breakout-v1`` -> MinAtar's
    ``register_envs``). Ids without a namespace, with a ``module:`` prefix (which ``gym.make``
    imports itself) or without such an entry point are returned as they are, for ``gym.make`` to
    accept or to reject with its own message."""
    if ":" in env_id or "/" not in env_id or env_id in gym.registry:
        return env_id
    namespace = env_id.split("/", 1)[0]
    for entry_point in entry_points(group=PLUGIN_GROUP):
        if entry_point.name == namespace:
            entry_point.load()()
            break
    return env_id
