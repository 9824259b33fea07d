import numpy as np
import pytest
import torch as th

from sb3_hgrn import SACHGRN, SoftHGRN, make_graph_vec_env
from sb3_hgrn.common.hgrn import PAPER_SIZE
from sb3_hgrn.presets import PRESETS, make_model, merge, preset_kwargs

SMALL_SURVIVING = dict(n_agents=6, map_size=10, max_cycles=20, n_resources=2)


def small_surviving(n_envs=2, seed=0):
    return make_graph_vec_env("surviving_v0", n_envs=n_envs, seed=seed, env_kwargs=SMALL_SURVIVING)


@pytest.mark.parametrize("name", list(PRESETS))
def test_preset_learns_and_round_trips(name, tmp_path):
    env = small_surviving()
    model = make_model(name, env, learning_starts=60, batch_size=4, train_freq=2, seed=0,
                       policy_kwargs=dict(hidden_dim=16, n_heads=2))  # fmt: skip
    model.learn(12 * 40)
    assert model._n_updates > 0
    model.save(tmp_path / "model.zip")
    obs = env.reset()
    expected, expected_state = model.predict(obs, deterministic=True)
    loaded = type(model).load(tmp_path / "model.zip", env=env)
    actions, state = loaded.predict(obs, deterministic=True)
    np.testing.assert_array_equal(actions, expected)
    np.testing.assert_allclose(state[0], expected_state[0], atol=1e-6)
    # every preset deploys the Polyak average of its acting network, and saves it
    policy = loaded.policy
    assert policy.average_tau == 0.002 and policy.deployed_network is policy.average_network
    assert int(policy.average_network.n_averaged) == model._n_updates


def test_presets_configure_the_ablations():
    env = small_surviving(n_envs=1)
    assert make_model("dgn", env).policy.q_net.gru is None and not make_model("dgn", env).stochastic
    assert make_model("soft_hgrn-G", env).policy.q_net.comm1.__class__.__name__ == "SelfOnly"
    assert make_model("commnet", env).policy.q_net.comm1.__class__.__name__ == "MeanCommunication"
    maac = make_model("maac", env)
    assert isinstance(maac, SACHGRN) and not maac.learn_alpha
    assert maac.policy.actor.comm1.__class__.__name__ == "SelfOnly" and maac.policy.actor.gru is None
    assert maac.policy.critics[0].comm1.__class__.__name__ == "GraphAttention"
    assert make_model("maac", env, learn_alpha=True).learn_alpha
    sac = make_model("sac_hgrn-R", env, policy_kwargs=dict(n_critics=2))
    assert len(sac.policy.critics) == 2 and sac.policy.actor.gru is None
    for name in ("soft_hgrn", "soft_hgrn-S", "sac_hgrn", "sac_hgrn-S"):
        assert make_model(name, env).reward_scale == "auto"
    unscaled = ("dqn", "commnet", "dgn", "hgn", "maac")
    assert all(make_model(name, env).reward_scale == 1.0 for name in unscaled)
    # SAC-HGRN collects with its critic's Boltzmann policy and 30 % random actions; MAAC as the paper
    sac = make_model("sac_hgrn", env)
    assert sac.behaviour_policy == "critic" and sac.exploration_rate == 0.3 and sac.alpha_max_step == 0.05
    assert sac.critic_target == "boltzmann"
    assert maac.behaviour_policy == "actor" and maac.exploration_rate == 0.0 and maac.critic_target == "actor"


def test_paper_presets_use_the_paper_size_and_schedule():
    algorithm, kwargs = preset_kwargs("soft_hgrn-S", paper=True, n_envs=100)
    assert algorithm is SoftHGRN and kwargs["stochastic"] is False
    assert kwargs["policy_kwargs"] == PAPER_SIZE and kwargs["batch_size"] == 128
    assert kwargs["buffer_size"] == 50_000 * 100 and kwargs["tau"] == 1.0 and kwargs["reward_scale"] == 1.0
    _, sac_kwargs = preset_kwargs("sac_hgrn", paper=True)
    assert sac_kwargs["behaviour_policy"] == "actor" and sac_kwargs["reward_scale"] == 1.0
    assert sac_kwargs["critic_target"] == "actor"
    _, kwargs = preset_kwargs("maac", paper=True)
    assert kwargs["policy_kwargs"]["hidden_dim"] == 256 and kwargs["tau"] == 0.01
    assert (kwargs["exploration_initial_eps"], kwargs["exploration_final_eps"]) == (0.9, 0.3)
    assert kwargs["policy_kwargs"]["actor_kwargs"] == {"communication": "none", "recurrent": False}


def test_merge_and_unknown_preset():
    assert merge({"a": 1, "p": {"x": 1, "y": 2}}, {"p": {"y": 3}, "b": 2}) == {
        "a": 1,
        "p": {"x": 1, "y": 3},
        "b": 2,
    }
    with pytest.raises(ValueError, match="Unknown preset"):
        make_model("qmix", small_surviving(n_envs=1))


@pytest.mark.parametrize("algorithm", [SoftHGRN, SACHGRN])
def test_temperature_moves_toward_the_target_on_a_controlled_batch(algorithm):
    """A uniform policy (entropy log|A| above a target of 0.1 log|A|) lowers alpha; a near-greedy one
    raises it. The policy is ``softmax(Q / alpha)`` of the Q-network, SAC-HGRN's critic by default."""
    env = small_surviving(n_envs=1)
    model = algorithm("GraphPolicy", env, learning_starts=0, target_entropy_ratio=0.1, alpha_optimizer="sgd",
                      alpha_learning_rate=1.0, policy_kwargs=dict(hidden_dim=16), seed=0)  # fmt: skip
    model.learn(6 * 10)
    policy = model.policy
    head = (policy.q_net if algorithm is SoftHGRN else policy.critics[0]).head[0]
    for scale, direction in ((0.0, -1), (1e4, +1)):
        with th.no_grad():
            head.weight.normal_().mul_(scale)
            head.bias.zero_()
        model.learning_rate = 0.0  # keep the network as set: only alpha may move
        model._setup_lr_schedule()
        before = policy.temperature.alpha.item()
        model.train(gradient_steps=1, batch_size=8)
        after = policy.temperature.alpha.item()
        assert (after - before) * direction > 0
        assert abs(after - before) == pytest.approx(model.alpha_max_step * before, rel=1e-4)  # the clip


def test_homogeneous_twins_attend_within_their_own_group_on_ctc():
    env = make_graph_vec_env(
        "ctc_v0", env_kwargs=dict(n_hunters=3, n_red_banks=2, n_blue_banks=2, map_size=12, max_cycles=10)
    )
    for name, across_groups in (("dgn", False), ("hgn", True), ("soft_dgrn", False), ("soft_hgrn", True)):
        model = make_model(name, env, policy_kwargs=dict(hidden_dim=16))
        assert model.policy.q_net.comm1.across_groups is across_groups
        assert len(model.policy.q_net.head.members) == 3
    sac = make_model("sac_dgrn", env, policy_kwargs=dict(hidden_dim=16))
    assert not sac.policy.actor.comm1.across_groups and not sac.policy.critics[0].comm2.across_groups
