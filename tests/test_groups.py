"""Heterogeneous agent groups end to end: VecEnv keys, grouped networks, per-group temperature."""

import math

import gymnasium as gym
import numpy as np
import pytest
import torch as th

from sb3_hgrn import SACHGRN, SoftHGRN, evaluate_graph_policy, make_graph_vec_env
from sb3_hgrn.common.soft_math import soft_value
from tests.toy_envs import NeighborBitEnv, SignalReaderEnv

CTC_SMALL = dict(n_hunters=4, n_red_banks=2, n_blue_banks=2, map_size=12, max_cycles=20)


def signal_env(n_envs: int = 4, seed: int = 0):
    return make_graph_vec_env(lambda: SignalReaderEnv(n_pairs=3), n_envs=n_envs, seed=seed)


def test_vec_env_carries_groups_action_masks_and_padding():
    env = signal_env(n_envs=2)
    assert set(env.observation_space.spaces) == {"obs", "neighbors", "group", "action_mask"}
    assert env.group_n_actions == (2, 3) and env.action_space.n == 3
    obs = env.reset()
    np.testing.assert_array_equal(obs["group"], [0, 0, 0, 1, 1, 1] * 2)
    np.testing.assert_array_equal(obs["action_mask"][:3], [[1, 1, 0]] * 3)
    np.testing.assert_array_equal(obs["action_mask"][3:6], [[1, 1, 1]] * 3)
    assert (obs["obs"][3:6] == 0).all() and (obs["obs"][:3, 1] == 1).all()  # readers padded with zeros
    for _ in range(8):
        obs, _, dones, infos = env.step(np.zeros(12, dtype=np.int64))
    assert dones.all()
    terminal = infos[4]["terminal_observation"]
    assert terminal["group"] == 1 and list(terminal["action_mask"]) == [1, 1, 1]
    assert infos[0]["team_episode"]["final_observation"]["group"].shape == (6,)


def test_env_copies_must_share_groups_and_actions_must_be_discrete():
    env = make_graph_vec_env("ctc_v0", env_kwargs=CTC_SMALL)
    assert [group.name for group in env.groups] == ["hunter", "red_bank", "blue_bank"]
    assert env.group_n_actions == (7, 5, 5)


@pytest.mark.parametrize("algorithm", [SoftHGRN, SACHGRN])
def test_learns_a_task_that_needs_messages_from_the_other_group(algorithm):
    """Readers must copy their signaller's bit (team optimum 48 per episode; without hearing the
    signallers readers score half, 36 in all). Invalid signaller actions would raise in the env."""
    returns = {}
    for communication in ("hgat", "none"):
        model = algorithm(
            "GraphPolicy", signal_env(), learning_starts=256, batch_size=16, train_freq=1,
            target_entropy_ratio=0.05, policy_kwargs=dict(hidden_dim=32, communication=communication), seed=0,
        )  # fmt: skip
        model.learn(20_000)
        returns[communication], _ = evaluate_graph_policy(model, signal_env(seed=100), n_eval_episodes=16)
    assert returns["hgat"] >= 45.0
    assert returns["none"] <= 40.0


def test_sampling_and_exploration_never_pick_an_action_the_group_lacks():
    env = make_graph_vec_env("ctc_v0", n_envs=2, seed=0, env_kwargs=CTC_SMALL)
    model = SoftHGRN("GraphPolicy", env, learning_starts=200, train_freq=1, exploration_initial_eps=0.5,
                     alpha_init=100.0, learn_alpha=False, policy_kwargs=dict(hidden_dim=16),
                     seed=0)  # fmt: skip
    model.learn(1_000)
    buffer = model.replay_buffer
    stored = buffer.actions[: buffer.pos]
    banks = buffer.groups[: buffer.pos] > 0
    assert stored[banks].max() <= 4 and stored[~banks].max() == 6  # hunters use all 7 actions
    obs = env.reset()
    for deterministic in (False, True):
        actions, _ = model.predict(obs, deterministic=deterministic)
        assert (actions < obs["action_mask"].sum(axis=1)).all()


def test_soft_value_and_entropy_ignore_the_masked_actions():
    env = make_graph_vec_env("ctc_v0", env_kwargs=CTC_SMALL)
    model = SoftHGRN("GraphPolicy", env, policy_kwargs=dict(hidden_dim=16), seed=0)
    obs, neighbors, groups = model.policy.to_graphs(model.policy.obs_to_tensor(env.reset())[0])
    q_values, _ = model.policy.q_net(obs, neighbors, th.zeros(1, 8, 16), groups)
    alpha = th.tensor([0.5])
    bank_q = q_values[0, 4:, :5]
    expected = 0.5 * th.logsumexp(bank_q / 0.5, dim=-1)
    th.testing.assert_close(soft_value(q_values, alpha)[0, 4:], expected)
    from sb3_hgrn.common.temperature import categorical_entropy

    th.testing.assert_close(categorical_entropy(q_values / alpha)[0, 4:], categorical_entropy(bank_q / alpha))


def test_every_group_has_its_own_target_entropy_and_alpha():
    env = make_graph_vec_env("ctc_v0", env_kwargs=CTC_SMALL)
    model = SoftHGRN("GraphPolicy", env, learning_starts=0, target_entropy_ratio=0.1, alpha_optimizer="sgd",
                     alpha_learning_rate=1.0, policy_kwargs=dict(hidden_dim=16), seed=0)  # fmt: skip
    assert model.target_entropy == pytest.approx([0.1 * math.log(7), 0.1 * math.log(5), 0.1 * math.log(5)])
    model.learn(8 * 20)
    heads = model.policy.q_net.head
    with th.no_grad():  # hunters uniform (entropy above target), banks near greedy (below)
        heads[0].weight.zero_()
        heads[0].bias.zero_()
        for bank_group in (1, 2):
            heads[bank_group].weight.normal_().mul_(1e4)
    model.learning_rate = 0.0
    model._setup_lr_schedule()
    before = model.policy.temperature.alpha.detach().clone()
    model.train(gradient_steps=1, batch_size=8)
    change = model.policy.temperature.alpha.detach() - before
    assert change[0] < 0 and (change[1:] > 0).all()
    th.testing.assert_close(change.abs(), model.alpha_max_step * before)


@pytest.mark.parametrize("algorithm", [SoftHGRN, SACHGRN])
def test_save_load_and_transfer_to_another_agent_count(tmp_path, algorithm):
    env = make_graph_vec_env("ctc_v0", n_envs=2, seed=0, env_kwargs=CTC_SMALL)
    model = algorithm(
        "GraphPolicy", env, learning_starts=100, train_freq=1, policy_kwargs=dict(hidden_dim=16), seed=0
    )
    model.learn(400)
    model.save(tmp_path / "ctc.zip")
    obs = env.reset()
    expected, _ = model.predict(obs, deterministic=True)
    loaded = algorithm.load(tmp_path / "ctc.zip", env=env)
    np.testing.assert_array_equal(loaded.predict(obs, deterministic=True)[0], expected)
    np.testing.assert_array_equal(
        loaded.policy.temperature.alpha.detach(), model.policy.temperature.alpha.detach()
    )

    more_hunters = make_graph_vec_env("ctc_v0", seed=1, env_kwargs={**CTC_SMALL, "n_hunters": 9})
    transferred = algorithm.load(tmp_path / "ctc.zip", env=more_hunters)
    assert transferred.policy.n_agents == 13
    mean, _ = evaluate_graph_policy(transferred, more_hunters, n_eval_episodes=1)
    assert np.isfinite(mean)
    transferred.learn(13 * 10, reset_num_timesteps=False)


def test_model_and_env_with_other_groups_do_not_mix(tmp_path):
    model = SoftHGRN("GraphPolicy", signal_env(), policy_kwargs=dict(hidden_dim=16))
    with pytest.raises(ValueError, match="spaces|groups"):
        model.set_env(make_graph_vec_env("ctc_v0", env_kwargs=CTC_SMALL))
    with pytest.raises(ValueError, match="spaces|groups"):
        model.set_env(make_graph_vec_env(lambda: NeighborBitEnv(4)))


def test_groups_that_do_not_fit_the_env_are_rejected():
    class BadIds(SignalReaderEnv):
        def __init__(self):
            super().__init__(n_pairs=2)
            self.group_ids = [0, 1, 2, 1]

    class TooManyActions(SignalReaderEnv):
        def __init__(self):
            super().__init__(n_pairs=2)
            self.shared_action_space = gym.spaces.Discrete(2)

    with pytest.raises(ValueError, match="group_ids"):
        make_graph_vec_env(BadIds)
    with pytest.raises(ValueError, match="shared spaces"):
        make_graph_vec_env(TooManyActions)
