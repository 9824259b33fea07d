"""Small many-agent envs for the tests, and the training set-up of the learning tests
(``tests/test_learning.py``, ``benchmarks/learning_tasks.py``)."""

from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import numpy as np
import torch as th
from pettingzoo import ParallelEnv

from sb3_hgrn import SACHGRN, SoftHGRN, evaluate_graph_policy, make_graph_vec_env
from sb3_hgrn.envs.base import AgentGroup, GraphParallelEnv, padded_observation_space


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


class BadValueEnv(DictOnlyEnv):
    """:class:`DictOnlyEnv` (3 agents, observations in ``[-1, 1]``) where agent 1 observes ``value``
    from step 3 on, and whose neighbour indices are offset by ``offset``."""

    def __init__(self, value: float = 0.5, offset: float = 0):
        super().__init__(max_cycles=5)
        self.value, self.offset = value, offset

    def step(self, actions):
        observations, *rest = super().step(actions)
        if self._t >= 3:
            observations["a1"][0] = self.value
        return (observations, *rest)

    def neighbors(self):
        return super().neighbors() + self.offset


def prefer_action(network: th.nn.Module, action: int) -> None:
    """Make ``network`` output 10 for ``action`` and 0 for the others on every observation (its last
    ``Linear`` layer, the head, gives a constant)."""
    head = [module for module in network.modules() if isinstance(module, th.nn.Linear)][-1]
    with th.no_grad():
        head.weight.zero_()
        head.bias.zero_()
        head.bias[action] = 10.0


def bit_vec_env(n_envs: int = 4, n_agents: int = 4, seed: int = 0):
    """Graph VecEnv of ``n_envs`` copies of :class:`NeighborBitEnv` with 8-step episodes."""
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


class CornerViewEnv(GraphParallelEnv):
    """Agents on a ring, each with a channel-last ``(size, size, 3)`` uint8 view: a 1 in channel 0
    at one of the view's four corners (drawn afresh every step), random bits in channel 1, zeros in
    channel 2. An agent earns 1 for naming its corner (actions 0..3: top-left, top-right,
    bottom-left, bottom-right); guessing earns 0.25 per agent-step."""

    metadata = {"render_modes": [], "name": "corner_view"}

    def __init__(self, n_agents: int = 4, size: int = 5, max_cycles: int = 8):
        self.possible_agents = [f"agent_{i}" for i in range(n_agents)]
        self.shared_observation_space = gym.spaces.Box(0, 1, shape=(size, size, 3), dtype=np.uint8)
        self.shared_action_space = gym.spaces.Discrete(4)
        self.max_neighbors = 2
        self.max_cycles = max_cycles
        self.render_mode = None
        self._rng = np.random.default_rng()
        self._graph = np.stack([np.arange(n_agents), (np.arange(n_agents) - 1) % n_agents], axis=1)

    def _draw(self) -> np.ndarray:
        size = self.shared_observation_space.shape[0]
        self._corners = self._rng.integers(0, 4, size=self.n_agents)
        views = np.zeros((self.n_agents, size, size, 3), dtype=np.uint8)
        rows, columns = (self._corners // 2) * (size - 1), (self._corners % 2) * (size - 1)
        views[np.arange(self.n_agents), rows, columns, 0] = 1
        views[..., 1] = self._rng.integers(0, 2, size=(self.n_agents, size, size))
        return views

    def reset_arrays(self, seed=None, options=None):
        if seed is not None:
            self._rng = np.random.default_rng(seed)
        self._t = 0
        return self._draw()

    def step_arrays(self, actions):
        rewards = (actions == self._corners).astype(np.float32)
        self._t += 1
        done = np.full(self.n_agents, self._t >= self.max_cycles)
        return self._draw(), rewards, np.zeros(self.n_agents, dtype=bool), done, {}

    def neighbors(self):
        return self._graph.copy()


class _IndependentAgentsEnv(GraphParallelEnv):
    """Base of the single-skill tasks below: agents that do not interact (each lists only itself)."""

    metadata = {"render_modes": [], "name": "independent_agents"}

    def __init__(self, n_agents: int, obs_dim: int, n_actions: int):
        self.possible_agents = [f"agent_{i}" for i in range(n_agents)]
        self.shared_observation_space = gym.spaces.Box(0, 1, shape=(obs_dim,), dtype=np.float32)
        self.shared_action_space = gym.spaces.Discrete(n_actions)
        self.max_neighbors = 1
        self.render_mode = None
        self._rng = np.random.default_rng()
        self._graph = np.arange(n_agents)[:, None]

    def _start(self) -> np.ndarray:
        """Set up a new episode and return its first observations ``(n_agents, obs_dim)``."""
        raise NotImplementedError

    def reset_arrays(self, seed=None, options=None):
        if seed is not None:
            self._rng = np.random.default_rng(seed)
        self._t = 0
        return self._start()

    def neighbors(self):
        return self._graph.copy()


class CueMemoryEnv(_IndependentAgentsEnv):
    """Memory: each agent sees a random cue bit at the first step only, then ``delay`` blank steps,
    then a query step where it earns 1 for naming the cue; the episode then terminates. Without
    memory the best expected return is 0.5 per agent.

    Observation ``(3,)``: the cue (first step only), a first-step flag and a query flag."""

    def __init__(self, n_agents: int = 4, delay: int = 2):
        super().__init__(n_agents, obs_dim=3, n_actions=2)
        self.delay = delay

    def _observe(self) -> np.ndarray:
        obs = np.zeros((self.n_agents, 3), dtype=np.float32)
        if self._t == 0:
            obs[:, 0], obs[:, 1] = self._cues, 1.0
        obs[:, 2] = float(self._t == self.delay + 1)
        return obs

    def _start(self):
        self._cues = self._rng.integers(0, 2, size=self.n_agents)
        return self._observe()

    def step_arrays(self, actions):
        query = self._t == self.delay + 1
        rewards = ((actions == self._cues) & query).astype(np.float32)
        self._t += 1
        ended = np.full(self.n_agents, query)
        return self._observe(), rewards, ended, np.zeros(self.n_agents, dtype=bool), {}


class InvestEnv(_IndependentAgentsEnv):
    """Delayed reward and real terminations: every step an agent consumes (+0.2 now) or invests
    (-0.5 now, +1 at the next step). The episode terminates after ``max_cycles`` steps, and the
    observation shows the last step and whether a payout is due.

    Investing pays ``-0.5 + gamma * 1`` against 0.2 for consuming, so a learner that bootstraps
    invests; on the last step nothing follows, so it consumes. A learner that does not bootstrap
    never invests (return 1.0 per agent over 5 steps); one that bootstraps through the termination
    also invests on the last step (1.5). The optimum is 2.2. With ``time_limit=True`` the episode is
    truncated instead of terminated: the payout still counts in the values, so a learner that
    bootstraps at time limits (as it must) invests on the last step too.

    Observation ``(2,)``: last-step flag, payout-due flag."""

    def __init__(self, n_agents: int = 4, max_cycles: int = 5, time_limit: bool = False):
        super().__init__(n_agents, obs_dim=2, n_actions=2)
        self.max_cycles, self.time_limit = max_cycles, time_limit

    def _observe(self) -> np.ndarray:
        last = np.full(self.n_agents, self._t == self.max_cycles - 1, dtype=np.float32)
        return np.stack([last, self._due.astype(np.float32)], axis=1)

    def _start(self):
        self._due = np.zeros(self.n_agents, dtype=bool)
        return self._observe()

    def step_arrays(self, actions):
        invest = actions == 1
        rewards = (np.where(invest, -0.5, 0.2) + self._due).astype(np.float32)
        self._due = invest
        self._t += 1
        ended = np.full(self.n_agents, self._t >= self.max_cycles)
        no_end = np.zeros(self.n_agents, dtype=bool)
        terminated, truncated = (no_end, ended) if self.time_limit else (ended, no_end)
        return self._observe(), rewards, terminated, truncated, {}


class TagEnv(_IndependentAgentsEnv):
    """A costly but necessary action: each step a target is in reach of an agent with probability
    ``p_target`` (shown as a bit). Of ``n_actions`` actions the last one tags: +1 with a target in
    reach, ``-penalty`` without; the others earn 0. Tagging whenever a target is in reach earns
    ``p_target`` per agent-step; never tagging earns 0."""

    def __init__(self, n_agents: int = 4, n_actions: int = 6, p_target: float = 0.2,
                 penalty: float = 0.2, max_cycles: int = 10):  # fmt: skip
        super().__init__(n_agents, obs_dim=1, n_actions=n_actions)
        self.p_target, self.penalty, self.max_cycles = p_target, penalty, max_cycles

    def _start(self):
        self._targets = self._rng.random(self.n_agents) < self.p_target
        return self._targets[:, None].astype(np.float32)

    def step_arrays(self, actions):
        tags = actions == self.shared_action_space.n - 1
        rewards = np.where(tags, np.where(self._targets, 1.0, -self.penalty), 0.0).astype(np.float32)
        self._t += 1
        truncated = np.full(self.n_agents, self._t >= self.max_cycles)
        return self._start(), rewards, np.zeros(self.n_agents, dtype=bool), truncated, {}


def costly_tag_env() -> TagEnv:
    """The tag task of the learning tests: 9 actions, a target in reach 10 % of the time, a 0.5 penalty."""
    return TagEnv(4, n_actions=9, p_target=0.1, penalty=0.5)


ALGORITHMS = {"SoftHGRN": SoftHGRN, "SACHGRN": SACHGRN}


def train_on(algorithm: str, make_env, timesteps: int, seed: int = 0, policy_kwargs=None, **kwargs):
    """A small model of ``algorithm`` (``"SoftHGRN"`` or ``"SACHGRN"``) trained for ``timesteps``
    agent-steps on 4 copies of ``make_env()``; ``kwargs`` override the algorithm's arguments."""
    options = dict(
        learning_starts=256, batch_size=16, train_freq=1, target_entropy_ratio=0.05, seed=seed,
        policy_kwargs=dict(hidden_dim=32, n_heads=2, **(policy_kwargs or {})),
    )  # fmt: skip
    options.update(kwargs)
    env = make_graph_vec_env(make_env, n_envs=4, seed=seed)
    return ALGORITHMS[algorithm]("GraphPolicy", env, **options).learn(timesteps)


def greedy_return(model, make_env, n_episodes: int = 16, seed: int = 100) -> float:
    """Mean team return of ``model``'s greedy actions over ``n_episodes`` episodes of ``make_env()``."""
    env = make_graph_vec_env(make_env, n_envs=1, seed=seed)
    return evaluate_graph_policy(model, env, n_eval_episodes=n_episodes, deterministic=True)[0]


def check_deployed_average(model, env, folder: Path) -> None:
    """Check, on a ``model`` trained with ``average_tau=0.1`` on the graph VecEnv ``env``, that its
    policy deploys the Polyak average of its acting network (Q-network or actor): one more update
    moves it by ``max(0.1, 1 / (1 + n / 10))`` after ``n`` updates, ``predict`` acts with it, the
    online network collects, and save/load keeps it (the zip is written into ``folder``)."""
    policy = model.policy
    average, online = list(policy.average_network.parameters()), list(policy.online_network.parameters())
    assert not all(th.equal(a, b) for a, b in zip(average, online, strict=True))
    weight = max(0.1, 1 / (1 + int(policy.average_network.n_averaged) / 10))  # the last tenth, then tau
    expected = [(1 - weight) * a + weight * b for a, b in zip(average, online, strict=True)]
    policy.update_average()
    for updated, value in zip(policy.average_network.parameters(), expected, strict=True):
        th.testing.assert_close(updated, value)

    obs = env.reset()
    obs_tensor, _ = policy.obs_to_tensor(obs)
    hidden = th.zeros(env.num_envs, policy.state_dim)
    with th.no_grad():
        _, average_state = policy.act_with(policy.average_network, obs_tensor, hidden, deterministic=True)
        _, online_state = policy.act_with(policy.online_network, obs_tensor, hidden, deterministic=True)
        _, collected_state = model._behaviour_act(obs_tensor, hidden)
    assert not th.allclose(average_state, online_state)
    _, predicted_state = model.predict(obs, deterministic=True)
    acting = [network is policy.online_network for network in policy.recurrent_networks].index(True)
    predicted, averaged = (
        policy.split_state(th.as_tensor(state).reshape(average_state.shape))[acting]
        for state in (predicted_state[0][0], average_state)
    )
    th.testing.assert_close(predicted, averaged, atol=1e-6, rtol=0)  # the acting network's memory
    th.testing.assert_close(collected_state, online_state)

    model.save(folder / "model.zip")
    loaded = type(model).load(folder / "model.zip", env=env)
    assert loaded.policy.average_tau == 0.1
    for a, b in zip(
        loaded.policy.average_network.parameters(), policy.average_network.parameters(), strict=True
    ):
        th.testing.assert_close(a, b)
