"""Base class of sb3_hgrn's many-agent environments: a PettingZoo ``ParallelEnv`` with an array API.

Every environment of ``sb3_hgrn.envs`` keeps its state in numpy arrays indexed by agent and
implements three array methods; this base class derives the PettingZoo dict API from them, so a
PettingZoo user sees an ordinary ``ParallelEnv`` while :class:`sb3_hgrn.common.vec_env.GraphVecEnv`
calls the array methods directly and never builds per-agent dicts.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from pettingzoo import ParallelEnv


class GraphParallelEnv(ParallelEnv):
    """A ``ParallelEnv`` whose agents share one observation and one action space and form a graph.

    Subclasses set ``possible_agents``, ``shared_observation_space``, ``shared_action_space`` and
    ``max_neighbors`` in ``__init__`` and implement :meth:`reset_arrays`, :meth:`step_arrays` and
    :meth:`neighbors`. Agent ``i`` is ``possible_agents[i]`` everywhere.
    """

    metadata: dict[str, Any] = {"render_modes": ["rgb_array", "human"], "name": "graph_env"}

    shared_observation_space: gym.spaces.Box
    shared_action_space: gym.spaces.Discrete
    max_neighbors: int

    # --- array API, implemented by subclasses -------------------------------------------------
    def reset_arrays(self, seed: int | None = None, options: dict | None = None) -> np.ndarray:
        """Start an episode. Returns observations ``(n_agents, obs_dim)``."""
        raise NotImplementedError

    def step_arrays(
        self, actions: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """Advance one step with ``actions`` of shape ``(n_agents,)``.

        Returns ``(observations (n_agents, obs_dim), rewards (n_agents,) float32,
        terminated (n_agents,) bool, truncated (n_agents,) bool, team_info)`` where ``team_info``
        is a dict of team-level figures (copied into every agent's info by the dict API).
        """
        raise NotImplementedError

    def neighbors(self) -> np.ndarray:
        """Current communication graph: ``(n_agents, max_neighbors)`` int64 agent indices.

        Row ``i`` starts with ``i`` itself, then its neighbours; unused entries are ``-1``.
        """
        raise NotImplementedError

    # --- PettingZoo API derived from the array API ---------------------------------------------
    @property
    def n_agents(self) -> int:
        return len(self.possible_agents)

    def observation_space(self, agent: str) -> gym.spaces.Box:
        return self.shared_observation_space

    def action_space(self, agent: str) -> gym.spaces.Discrete:
        return self.shared_action_space

    def reset(
        self, seed: int | None = None, options: dict | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, dict]]:
        observations = self.reset_arrays(seed=seed, options=options)
        self.agents = list(self.possible_agents)
        return dict(zip(self.agents, observations, strict=True)), {agent: {} for agent in self.agents}

    def step(self, actions: dict[str, int]) -> tuple[dict, dict, dict, dict, dict]:
        if not self.agents:
            raise RuntimeError("step() called after the episode ended; call reset() first.")
        missing = set(self.agents) - set(actions)
        if missing:
            raise ValueError(f"No action given for agents {sorted(missing)[:5]}.")
        action_array = np.fromiter((actions[agent] for agent in self.agents), dtype=np.int64)
        observations, rewards, terminated, truncated, team_info = self.step_arrays(action_array)
        agents = self.agents
        result = (
            dict(zip(agents, observations, strict=True)),
            dict(zip(agents, rewards.tolist(), strict=True)),
            dict(zip(agents, terminated.tolist(), strict=True)),
            dict(zip(agents, truncated.tolist(), strict=True)),
            {agent: dict(team_info) for agent in agents},
        )
        if np.all(terminated | truncated):
            self.agents = []
        return result
