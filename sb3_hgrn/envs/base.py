"""Base class of sb3_hgrn's many-agent environments: a PettingZoo ``ParallelEnv`` with an array API.

Every environment of ``sb3_hgrn.envs`` keeps its state in numpy arrays indexed by agent and
implements three array methods; this base class derives the PettingZoo dict API from them, so a
PettingZoo user sees an ordinary ``ParallelEnv`` while :class:`sb3_hgrn.common.vec_env.GraphVecEnv`
calls the array methods directly and never builds per-agent dicts.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, NamedTuple

import gymnasium as gym
import numpy as np
from pettingzoo import ParallelEnv

from sb3_hgrn.envs.rendering import PygameWindow
from sb3_hgrn.validation import check_integer


class AgentGroup(NamedTuple):
    """A group of agents sharing spaces (and, in the models, parameters)."""

    name: str
    observation_space: gym.spaces.Box  # 1-D (padded to the widest group), or the shared n-D shape
    action_space: gym.spaces.Discrete


def check_agent_count(name: str, count: Any, maximum: int | None = None, why: str = "") -> None:
    """Raise a ``ValueError`` unless ``count`` is an integer in ``1..maximum`` (``>= 1`` without a
    maximum): the rule for the agent counts of every env (one agent makes a graph of its own; ``why``
    says where the maximum comes from)."""
    check_integer(name, count, 1, maximum, why)


def binary_table(n_values: int, n_bits: int, dtype: np.dtype = np.int8) -> np.ndarray:
    """``(n_values, n_bits)``: row ``v`` is ``v`` in binary, most significant bit first (the
    position and index codes of the envs' observations)."""
    shifts = np.arange(n_bits - 1, -1, -1)
    return ((np.arange(n_values)[:, None] >> shifts) & 1).astype(dtype)


def padded_observation_space(groups: Sequence[AgentGroup]) -> gym.spaces.Box:
    """The 1-D Box holding every group's observation padded with zeros to the widest one."""
    width = max(group.observation_space.shape[0] for group in groups)
    dtype = np.result_type(*(group.observation_space.dtype for group in groups))
    low, high = np.zeros(width, dtype=dtype), np.zeros(width, dtype=dtype)
    for group in groups:
        dim = group.observation_space.shape[0]
        low[:dim] = np.minimum(low[:dim], group.observation_space.low)
        high[:dim] = np.maximum(high[:dim], group.observation_space.high)
    return gym.spaces.Box(low, high, dtype=dtype)


class GraphParallelEnv(ParallelEnv):
    """A ``ParallelEnv`` whose agents form a graph and fall into groups with shared spaces.

    Subclasses set ``possible_agents``, ``shared_observation_space``, ``shared_action_space`` and
    ``max_neighbors`` in ``__init__`` and implement :meth:`reset_arrays`, :meth:`step_arrays` and
    :meth:`neighbors`. Agent ``i`` is ``possible_agents[i]`` everywhere.

    Homogeneous envs have one group. A heterogeneous env also sets ``groups`` (one
    :class:`AgentGroup` each) and ``group_ids`` ``(n_agents,)`` (the group of every agent); its
    shared spaces are the widest: ``padded_observation_space(groups)`` and ``Discrete`` of the
    largest action count. The array API then carries every observation zero-padded to the shared
    width (group ``g`` fills the first ``groups[g].observation_space.shape[0]`` entries; observations
    of more dimensions are not padded: every group then observes the shared shape) and
    takes actions below each agent's own group's action count; the dict API gives every agent its
    own group's spaces.
    """

    metadata: dict[str, Any] = {"render_modes": ["rgb_array", "human"], "name": "graph_env"}

    shared_observation_space: gym.spaces.Box
    shared_action_space: gym.spaces.Discrete
    max_neighbors: int
    render_mode: str | None = None
    _window: PygameWindow | None = None
    _neighbor_cache: np.ndarray | None = None

    # --- array API, implemented by subclasses -------------------------------------------------
    def reset_arrays(self, seed: int | None = None, options: dict | None = None) -> np.ndarray:
        """Start an episode. Returns observations ``(n_agents, *obs_shape)``."""
        raise NotImplementedError

    def step_arrays(
        self, actions: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """Advance one step with ``actions`` of shape ``(n_agents,)``.

        Returns ``(observations (n_agents, *obs_shape), rewards (n_agents,) float32,
        terminated (n_agents,) bool, truncated (n_agents,) bool, team_info)`` where ``team_info``
        is a dict of team-level figures (copied into every agent's info by the dict API).
        """
        raise NotImplementedError

    def neighbors(self) -> np.ndarray:
        """Current communication graph: ``(n_agents, max_neighbors)`` int64 agent indices.

        Row ``i`` starts with ``i`` itself, then its neighbours; unused entries are ``-1``. Computed by
        :meth:`_neighbor_lists` at most once per step (subclasses set ``_neighbor_cache = None`` when
        agents move) and returned read-only.
        """
        if self._neighbor_cache is None:
            graph = self._neighbor_lists()
            graph.flags.writeable = False
            self._neighbor_cache = graph
        return self._neighbor_cache

    def _neighbor_lists(self) -> np.ndarray:
        """The communication graph of the current state (see :meth:`neighbors`)."""
        raise NotImplementedError

    @property
    def alive(self) -> np.ndarray:
        """``(n_agents,)`` bool: the agents still in the episode. Agents of the envs built on this
        class never leave before the episode ends, so all are; an env whose agents die or leave
        says which are gone (see :class:`~sb3_hgrn.common.vec_env.ParallelEnvAdapter`)."""
        return np.ones(self.n_agents, dtype=bool)

    # --- pickling ---------------------------------------------------------------------------
    def _bind_views(self) -> None:
        """Set the attributes that are views into other arrays (none here). Subclasses that keep
        such views set them here, from ``__init__``: pickling copies every array on its own, so
        :meth:`__setstate__` calls this again to make them views of the unpickled arrays."""

    def __setstate__(self, state: dict[str, Any]) -> None:
        """Restore a pickled env, its views into its arrays bound again (see :meth:`_bind_views`)."""
        self.__dict__.update(state)
        self._bind_views()

    def _draw(self) -> np.ndarray:
        """The current state as an ``(height, width, 3)`` uint8 image (subclasses that render)."""
        raise NotImplementedError

    # --- rendering --------------------------------------------------------------------------
    def render(self) -> np.ndarray | None:
        """Draw the current state: ``"rgb_array"`` returns the image ``(height, width, 3)`` uint8,
        ``"human"`` shows it in a pygame window (see the subclass's ``_draw`` for what it shows)."""
        if self.render_mode is None:
            gym.logger.warn("render() called without a render_mode; pass render_mode='rgb_array' or 'human'.")
            return None
        image = self._draw()
        if self.render_mode == "rgb_array":
            return image
        if self._window is None:
            self._window = PygameWindow(self.metadata["name"], self.metadata.get("render_fps", 10))
        self._window.show(image)
        return None

    def close(self) -> None:
        """Close the pygame window if one was opened."""
        if self._window is not None:
            self._window.close()
            self._window = None

    # --- groups ------------------------------------------------------------------------------
    @property
    def n_agents(self) -> int:
        return len(self.possible_agents)

    @property
    def groups(self) -> tuple[AgentGroup, ...]:
        """The agent groups, in group-id order (one group ``"agent"`` unless a subclass sets them)."""
        return getattr(self, "_groups", None) or (
            AgentGroup("agent", self.shared_observation_space, self.shared_action_space),
        )

    @groups.setter
    def groups(self, groups: Sequence[AgentGroup]) -> None:
        self._groups = tuple(groups)

    @property
    def group_ids(self) -> np.ndarray:
        """``(n_agents,)`` int64 group id of every agent (all 0 unless a subclass sets them)."""
        ids = getattr(self, "_group_ids", None)
        return np.zeros(self.n_agents, dtype=np.int64) if ids is None else ids

    @group_ids.setter
    def group_ids(self, ids: np.ndarray) -> None:
        self._group_ids = np.asarray(ids, dtype=np.int64)

    def _agent_group(self, agent: str) -> AgentGroup:
        return self.groups[int(self.group_ids[self._agent_index[agent]])]

    @property
    def _agent_index(self) -> dict[str, int]:
        index = getattr(self, "_agent_index_cache", None)
        if index is None or len(index) != self.n_agents:
            index = {agent: i for i, agent in enumerate(self.possible_agents)}
            self._agent_index_cache = index
        return index

    # --- PettingZoo API derived from the array API ---------------------------------------------
    def observation_space(self, agent: str) -> gym.spaces.Box:
        return self._agent_group(agent).observation_space

    def action_space(self, agent: str) -> gym.spaces.Discrete:
        return self._agent_group(agent).action_space

    def _agent_observations(self, observations: np.ndarray) -> dict[str, np.ndarray]:
        """Per-agent dict of observations, each cut back to its own group's width."""
        if len(self.groups) == 1:
            return dict(zip(self.agents, observations, strict=True))
        widths = [group.observation_space.shape[0] for group in self.groups]
        return {
            agent: row[: widths[group]]
            for agent, row, group in zip(self.agents, observations, self.group_ids.tolist(), strict=True)
        }

    def reset(
        self, seed: int | None = None, options: dict | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, dict]]:
        observations = self.reset_arrays(seed=seed, options=options)
        self.agents = list(self.possible_agents)
        return self._agent_observations(observations), {agent: {} for agent in self.agents}

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
            self._agent_observations(observations),
            dict(zip(agents, rewards.tolist(), strict=True)),
            dict(zip(agents, terminated.tolist(), strict=True)),
            dict(zip(agents, truncated.tolist(), strict=True)),
            {agent: dict(team_info) for agent in agents},
        )
        if np.all(terminated | truncated):
            self.agents = []
        return result
