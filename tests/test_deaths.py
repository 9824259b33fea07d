"""Agents that die during an episode, in plain PettingZoo ParallelEnvs adapted by make_graph_vec_env."""

from __future__ import annotations

import csv

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from pettingzoo import ParallelEnv
from stable_baselines3.common.logger import configure

from sb3_hgrn import SACHGRN, SoftHGRN, evaluate_graph_policy
from sb3_hgrn.common.vec_env import GraphVecEnv, ParallelEnvAdapter

N_AGENTS = 4


class DyingEnv(ParallelEnv):
    """Agent ``i`` dies (terminates) at step ``deaths[i]`` (``None``: lives on); the episode is
    truncated after ``max_cycles`` steps. Every living agent earns 1 per step and lists every other
    living agent. With ``rewards_for_the_dead`` the env also reports a reward of 100 for every dead
    agent, which must count nowhere."""

    metadata = {"render_modes": [], "name": "dying"}

    def __init__(self, deaths, max_cycles: int = 6, rewards_for_the_dead: bool = False):
        self.possible_agents = [f"a{i}" for i in range(N_AGENTS)]
        self.deaths = deaths
        self.max_cycles = max_cycles
        self.rewards_for_the_dead = rewards_for_the_dead
        self.max_neighbors = N_AGENTS
        self.render_mode = None
        self.steps_taken = 0
        self.actions_seen: list[set[str]] = []

    def observation_space(self, agent):
        return gym.spaces.Box(0.0, 100.0, shape=(2,), dtype=np.float32)

    def action_space(self, agent):
        return gym.spaces.Discrete(2)

    def _observation(self, i: int) -> np.ndarray:
        return np.array([self._t, i], dtype=np.float32)

    def reset(self, seed=None, options=None):
        self.agents = list(self.possible_agents)
        self._t = 0
        return {a: self._observation(i) for i, a in enumerate(self.possible_agents)}, {}

    def step(self, actions):
        self.steps_taken += 1
        self.actions_seen.append(set(actions))
        self._t += 1
        index = {a: i for i, a in enumerate(self.possible_agents)}
        acting = list(self.agents)
        observations = {a: self._observation(index[a]) for a in acting}
        rewards = {a: 1.0 for a in acting}
        if self.rewards_for_the_dead:
            rewards.update({a: 100.0 for a in self.possible_agents if a not in acting})
        terminations = {a: self.deaths[index[a]] == self._t for a in acting}
        truncations = {a: self._t >= self.max_cycles for a in acting}
        self.agents = [a for a in acting if not (terminations[a] or truncations[a])]
        return observations, rewards, terminations, truncations, {a: {} for a in acting}

    def neighbors(self):
        """Every agent lists itself, then every other agent, dead or not (the VecEnv drops the dead)."""
        return (np.arange(N_AGENTS)[:, None] + np.arange(N_AGENTS)[None, :]) % N_AGENTS


def dying_vec_env(schedules, **kwargs) -> GraphVecEnv:
    """One copy of :class:`DyingEnv` per death schedule."""
    return GraphVecEnv([lambda deaths=deaths: DyingEnv(deaths, **kwargs) for deaths in schedules])


# copy 0: a0 dies at step 2, a2 at step 4, truncated at 6; copy 1: a1 and a2 die at step 1, a0 and
# a3 at step 3 (the copy ends and resets), and again in its second episode (steps 4 and 6)
SCHEDULES = [(2, None, 4, None), (3, 1, 1, 3)]
T, F = True, False
ALIVE_AFTER = {  # step: alive mask of both copies after it
    1: [[T, T, T, T], [T, F, F, T]],
    2: [[F, T, T, T], [T, F, F, T]],
    3: [[F, T, T, T], [T, T, T, T]],
    4: [[F, T, F, T], [T, F, F, T]],
    5: [[F, T, F, T], [T, F, F, T]],
    6: [[T, T, T, T], [T, T, T, T]],
}
DIED_AT = {1: [[F, F, F, F], [F, T, T, F]], 2: [[T, F, F, F], [F] * 4], 3: [[F] * 4, [T, F, F, T]],
           4: [[F, F, T, F], [F, T, T, F]], 5: [[F] * 4] * 2, 6: [[F] * 4, [T, F, F, T]]}  # fmt: skip
ENDED_AT = {3: [F, T], 6: [T, T]}


def check_living_lists(graph: np.ndarray, alive: np.ndarray) -> None:
    """Every living agent lists exactly the living agents of its copy; the dead list nobody."""
    for agent, row in enumerate(graph):
        expected = set(np.flatnonzero(alive).tolist()) if alive[agent] else set()
        assert set(row.tolist()) - {-1} == expected, f"agent {agent}"


def test_alive_mask_neighbours_terminations_and_resets():
    env = dying_vec_env(SCHEDULES, max_cycles=6)
    env.reset()
    assert env.alive.all()
    for step in range(1, 7):
        obs, _, dones, infos = env.step(np.zeros(env.num_envs, dtype=np.int64))
        alive = np.array(ALIVE_AFTER[step])
        np.testing.assert_array_equal(env.alive, alive.reshape(-1), err_msg=f"step {step}")
        np.testing.assert_array_equal(env.terminations, np.ravel(DIED_AT[step]), err_msg=f"step {step}")
        np.testing.assert_array_equal(dones, np.repeat(ENDED_AT.get(step, [F, F]), N_AGENTS))
        graph = obs["neighbors"].reshape(2, N_AGENTS, -1)
        for copy in range(2):
            check_living_lists(graph[copy], alive[copy])
    # copy 1's last agents died: its final graph has nobody; copy 0 was truncated with a1, a3 alive
    team = infos[N_AGENTS]["team_episode"]
    np.testing.assert_array_equal(team["terminated"], [T, F, F, T])
    assert (team["final_observation"]["neighbors"] == -1).all()
    final = infos[0]["team_episode"]["final_observation"]["neighbors"]
    check_living_lists(final, np.array([F, T, F, T]))
    assert [info["TimeLimit.truncated"] for info in infos[:N_AGENTS]] == [F, T, F, T]
    # the env got actions for its living agents only
    assert env.envs[0].env.actions_seen[2] == {"a1", "a2", "a3"}
    assert env.envs[0].env.actions_seen[4] == {"a1", "a3"}


def test_team_return_counts_each_agent_while_it_lives():
    env = dying_vec_env([(2, None, 4, None)], max_cycles=6, rewards_for_the_dead=True)
    env.reset()
    rewards = []
    for _ in range(6):
        _, reward, dones, infos = env.step(np.zeros(env.num_envs, dtype=np.int64))
        rewards.append(reward)
    assert dones.all()
    # a0 lives steps 1-2, a2 steps 1-4, a1 and a3 all 6
    assert infos[0]["team_episode"]["r"] == 2 + 4 + 6 + 6
    np.testing.assert_array_equal(np.stack(rewards)[:, 0], [1, 1, 0, 0, 0, 0])


class AbsentEnv(DyingEnv):
    """:class:`DyingEnv` whose last agent never takes part: it is not among the agents at reset."""

    def reset(self, seed=None, options=None):
        observations, infos = super().reset(seed, options)
        self.agents = self.possible_agents[:-1]
        return {a: observations[a] for a in self.agents}, infos


def test_per_agent_return_counts_only_the_agents_that_lived(tmp_path):
    env = GraphVecEnv([lambda: AbsentEnv((2, None, 4, None), max_cycles=6)])
    model = SoftHGRN("GraphPolicy", env, learning_starts=0, buffer_size=1000, seed=0)
    model.set_logger(configure(str(tmp_path), ["csv"]))
    model.learn(env.num_envs * 12, log_interval=1)
    rows = list(csv.DictReader((tmp_path / "progress.csv").open()))
    # a0 lives steps 1-2, a1 all 6, a2 steps 1-4; a3 never: 12 over 3 agents
    assert [float(row["rollout/ep_team_rew_mean"]) for row in rows] == [12.0, 12.0]
    assert [float(row["rollout/ep_rew_mean"]) for row in rows] == [4.0, 4.0]


def test_evaluation_counts_each_agent_while_it_lives():
    env = dying_vec_env([(2, None, 4, None)], max_cycles=6, rewards_for_the_dead=True)
    model = SoftHGRN("GraphPolicy", env, learning_starts=0, buffer_size=1000, seed=0)
    returns, lengths = evaluate_graph_policy(model, env, n_eval_episodes=2, return_episode_rewards=True)
    assert returns == [18.0, 18.0] and lengths == [6, 6]


def test_stepping_an_env_without_agents_raises_before_reaching_it():
    adapter = ParallelEnvAdapter(DyingEnv((1, 1, 1, 1)))
    adapter.reset_arrays()
    adapter.step_arrays(np.zeros(N_AGENTS, dtype=np.int64))
    assert not adapter.alive.any()
    with pytest.raises(RuntimeError, match="no agents left"):
        adapter.step_arrays(np.zeros(N_AGENTS, dtype=np.int64))
    assert adapter.env.steps_taken == 1


def quick_model(algorithm, env, **kwargs):
    return algorithm(
        "GraphPolicy", env, learning_starts=0, batch_size=8, buffer_size=4000, train_freq=1, seed=0,
        policy_kwargs={"hidden_dim": 16, "n_heads": 2, "head_dim": 8}, **kwargs,
    )  # fmt: skip


def garbage_copy(batch, dead: th.Tensor):
    """``batch`` with the stored values of the ``dead`` ``(batch, n_agents)`` bool entries replaced by
    random values (finite, of the right kinds); their neighbour lists stay (the VecEnv empties those
    of gone agents)."""
    generator = th.Generator().manual_seed(1)

    def replaced(tensor: th.Tensor, scale: float) -> th.Tensor:
        noise = th.rand(tensor.shape, generator=generator) * scale
        noise = noise.round() if not tensor.is_floating_point() else noise
        where = dead.view(*dead.shape, *([1] * (tensor.dim() - 2)))
        return th.where(where, noise.to(tensor.dtype), tensor)

    return batch._replace(
        observations=replaced(batch.observations, 100.0),
        next_observations=replaced(batch.next_observations, 100.0),
        actions=replaced(batch.actions, 1),
        rewards=replaced(batch.rewards, 50.0),
        terminated=replaced(batch.terminated, 1),
        hidden=replaced(batch.hidden, 3.0),
        next_hidden=replaced(batch.next_hidden, 3.0),
    )


def gradients_after_one_step(model, batch) -> list[th.Tensor]:
    """The gradients of every network and of the temperature (``H - H_target``) of one ``train``
    step on ``batch``; the policy's parameters are restored after it."""
    state = {key: value.clone() for key, value in model.policy.state_dict().items()}
    model.replay_buffer.sample_sequences = lambda *args, **kwargs: [batch]
    model.policy.zero_grad(set_to_none=True)
    th.manual_seed(0)
    model.train(gradient_steps=1, batch_size=len(batch.rewards))
    gradients = [p.grad.clone() for p in model.policy.parameters() if p.grad is not None]
    model.policy.load_state_dict(state)
    return gradients


@pytest.mark.parametrize("algorithm", [SoftHGRN, SACHGRN])
def test_dead_agents_add_nothing_to_any_loss(algorithm):
    env = dying_vec_env(SCHEDULES, max_cycles=6)
    model = quick_model(algorithm, env)
    model.learn(env.num_envs * 12)
    buffer = model.replay_buffer
    rows = np.arange(8)
    batch = buffer._get_samples(rows, rows % 2)
    dead = batch.alive == 0
    assert dead.any() and not dead.all()
    original = gradients_after_one_step(model, batch)
    garbage = gradients_after_one_step(model, garbage_copy(batch, dead))
    assert len(original) == len(garbage) > 1
    for before, after in zip(original, garbage, strict=True):
        assert th.equal(before, after)
    living_garbage = gradients_after_one_step(model, garbage_copy(batch, ~dead))
    assert not all(th.equal(a, b) for a, b in zip(original, living_garbage, strict=True))


@pytest.mark.parametrize("algorithm", [SoftHGRN, SACHGRN])
def test_training_through_deaths(algorithm):
    env = dying_vec_env(SCHEDULES, max_cycles=6)
    model = quick_model(algorithm, env)
    model.learn(env.num_envs * 300)
    buffer = model.replay_buffer
    stored_alive = buffer.alive[: buffer.pos]
    assert not stored_alive.all() and stored_alive.any(axis=2).all()  # every graph has a living agent
    # the death steps are stored as terminated, with their agent alive when it acted
    assert (buffer.terminated[: buffer.pos] <= stored_alive).all()
    assert buffer.terminated[: buffer.pos].any()
