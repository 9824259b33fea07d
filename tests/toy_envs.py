"""Small many-agent envs for the tests."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
from pettingzoo import ParallelEnv

from sb3_hgrn.common.graph_env import AgentGroup, GraphParallelEnv, padded_observation_space


class NeighborBitEnv(GraphParallelEnv):
    """Agents on a ring each see a fresh random bit; an agent earns 1 when its action is the bit of
    its left neighbour. Without communication the best expected reward is 0.5 per agent-step."""

    metadata = {"render_modes": [], "name": "neighbor_bit"}

    def __init__(self, n_agents: int = 4, max_cycles: int = 8):
        self.possible_agents = [f"agent_{i}" for i in range(n_agents)]
        self.shared_observation_space = gym.spaces.Box(0, 1, shape=(1,), dtype=np.int8)
        self.shared_action_space = gym.spaces.Discrete(2)
        self.max_neighbors = 2
        self.max_cycles = max_cycles
        self.render_mode = None
        self._rng = np.random.default_rng()
        self._graph = np.stack([np.arange(n_agents), (np.arange(n_agents) - 1) % n_agents], axis=1)

    def _draw(self) -> np.ndarray:
        self._bits = self._rng.integers(0, 2, size=self.n_agents).astype(np.int8)
        return self._bits[:, None].copy()

    def reset_arrays(self, seed=None, options=None):
        if seed is not None:
            self._rng = np.random.default_rng(seed)
        self._t = 0
        return self._draw()

    def step_arrays(self, actions):
        rewards = (actions == self._bits[self._graph[:, 1]]).astype(np.float32)
        self._t += 1
        done = np.full(self.n_agents, self._t >= self.max_cycles)
        return self._draw(), rewards, np.zeros(self.n_agents, dtype=bool), done, {}

    def neighbors(self):
        return self._graph.copy()


class DictOnlyEnv(ParallelEnv):
    """A plain ParallelEnv (dict API only) that supplies a graph: every agent sees everyone."""

    metadata = {"render_modes": [], "name": "dict_only"}

    def __init__(self, n_agents: int = 3, max_cycles: int = 5, reward: float = 1.0):
        self.possible_agents = [f"a{i}" for i in range(n_agents)]
        self.max_neighbors = n_agents
        self.max_cycles = max_cycles
        self.reward = reward
        self.render_mode = None

    def observation_space(self, agent):
        return gym.spaces.Box(-1.0, 1.0, shape=(2,), dtype=np.float32)

    def action_space(self, agent):
        return gym.spaces.Discrete(3)

    def reset(self, seed=None, options=None):
        self.agents = list(self.possible_agents)
        self._t = 0
        return {a: np.zeros(2, np.float32) for a in self.agents}, {a: {} for a in self.agents}

    def step(self, actions):
        self._t += 1
        obs = {a: np.full(2, self._t / self.max_cycles, np.float32) for a in self.agents}
        rewards = {a: self.reward * actions[a] for a in self.agents}
        truncated = {a: self._t >= self.max_cycles for a in self.agents}
        terminated = {a: False for a in self.agents}
        infos = {a: {} for a in self.agents}
        if self._t >= self.max_cycles:
            self.agents = []
        return obs, rewards, terminated, truncated, infos

    def neighbors(self):
        n = len(self.possible_agents)
        return (np.arange(n)[:, None] + np.arange(n)[None, :]) % n


def bit_vec_env(n_envs: int = 4, n_agents: int = 4, seed: int = 0):
    """Graph VecEnv of ``n_envs`` copies of :class:`NeighborBitEnv` with 8-step episodes."""
    from sb3_hgrn import make_graph_vec_env

    return make_graph_vec_env(lambda: NeighborBitEnv(n_agents, max_cycles=8), n_envs=n_envs, seed=seed)


class SignalReaderEnv(GraphParallelEnv):
    """Two agent groups: ``n_pairs`` signallers (observation: a fresh random bit and a 1; 2 actions)
    and ``n_pairs`` readers (observation: a 0; 3 actions). Signaller ``k`` earns 1 when its action is
    its own bit; reader ``k`` earns 1 when its action is the bit of signaller ``k``, its only
    neighbour, and 0 for its third action. Without communication a reader scores 0.5 at best."""

    metadata = {"render_modes": [], "name": "signal_reader"}

    def __init__(self, n_pairs: int = 3, max_cycles: int = 8):
        self.possible_agents = [f"signaller_{k}" for k in range(n_pairs)] + [
            f"reader_{k}" for k in range(n_pairs)
        ]
        self.groups = (
            AgentGroup("signaller", gym.spaces.Box(0, 1, shape=(2,), dtype=np.int8), gym.spaces.Discrete(2)),
            AgentGroup("reader", gym.spaces.Box(0, 0, shape=(1,), dtype=np.int8), gym.spaces.Discrete(3)),
        )
        self.group_ids = np.repeat([0, 1], n_pairs)
        self.shared_observation_space = padded_observation_space(self.groups)
        self.shared_action_space = gym.spaces.Discrete(3)
        self.max_neighbors = 2
        self.max_cycles = max_cycles
        self.render_mode = None
        self._rng = np.random.default_rng()
        partners = np.concatenate([np.arange(n_pairs), np.arange(n_pairs)])  # signaller k <-> reader k
        self._graph = np.stack([np.arange(2 * n_pairs), partners], axis=1)
        self._graph[:n_pairs, 1] = -1  # signallers listen to nobody

    def _draw(self) -> np.ndarray:
        n_pairs = self.n_agents // 2
        self._bits = self._rng.integers(0, 2, size=n_pairs).astype(np.int8)
        observations = np.zeros((self.n_agents, 2), dtype=np.int8)
        observations[:n_pairs, 0] = self._bits
        observations[:n_pairs, 1] = 1
        return observations

    def reset_arrays(self, seed=None, options=None):
        if seed is not None:
            self._rng = np.random.default_rng(seed)
        self._t = 0
        return self._draw()

    def step_arrays(self, actions):
        n_pairs = self.n_agents // 2
        if (actions[:n_pairs] >= 2).any():
            raise ValueError("signallers have 2 actions")
        rewards = (actions == np.concatenate([self._bits, self._bits])).astype(np.float32)
        self._t += 1
        done = np.full(self.n_agents, self._t >= self.max_cycles)
        return self._draw(), rewards, np.zeros(self.n_agents, dtype=bool), done, {}

    def neighbors(self):
        return self._graph.copy()
