import math

import numpy as np
import pytest
import torch as th

from sb3_hgrn import SACHGRN, DiscreteSAC, SoftDQN, SoftHGRN
from sb3_hgrn.common.soft_math import sample_actions
from sb3_hgrn.common.temperature import (
    FALLBACK_ALPHA,
    EntropyTemperature,
    TemperatureController,
    alpha_from_rewards,
    categorical_entropy,
    target_entropy,
)
from tests.toy_envs import TagEnv, bit_vec_env


@pytest.mark.parametrize("shape", [(64, 5), (8, 12, 21)])
def test_sampled_actions_are_the_draws_of_a_categorical_distribution(shape):
    """The policies' sampler draws what ``Categorical`` draws from the same generator state, so that
    runs seeded before it keep their actions; and the draws follow ``softmax(logits)``."""
    logits = th.randn(*shape) * 3
    th.manual_seed(0)
    expected = th.distributions.Categorical(logits=logits).sample()
    th.manual_seed(0)
    assert th.equal(sample_actions(logits), expected)
    many = sample_actions(logits[..., :1, :].expand(*shape[:-2], 20_000, shape[-1]))
    frequencies = th.nn.functional.one_hot(many, shape[-1]).float().mean(dim=-2)
    th.testing.assert_close(frequencies, th.softmax(logits[..., 0, :], dim=-1), atol=0.015, rtol=0)
    with pytest.raises(ValueError, match="logits are not finite"):
        sample_actions(logits.index_fill(-1, th.tensor([1]), float("nan")))


def test_target_entropy_and_categorical_entropy():
    assert target_entropy(0.3, 5) == pytest.approx(0.3 * math.log(5))
    with pytest.raises(ValueError, match="target_entropy_ratio"):
        target_entropy(1.5, 5)
    uniform = th.zeros(4)
    assert categorical_entropy(uniform).item() == pytest.approx(math.log(4))
    logits = th.tensor([math.log(0.75), math.log(0.25)])
    assert categorical_entropy(logits).item() == pytest.approx(
        -(0.75 * math.log(0.75) + 0.25 * math.log(0.25))
    )


@pytest.mark.parametrize("log_space", [False, True])
@pytest.mark.parametrize("optimizer", ["adam", "sgd"])
def test_alpha_falls_above_target_and_rises_below(optimizer, log_space):
    for entropy, direction in ((1.0, -1), (0.1, +1)):
        temperature = EntropyTemperature(0.5, log_space=log_space)
        controller = TemperatureController(temperature, target=0.5, optimizer=optimizer, learning_rate=0.1)
        before = temperature.alpha.item()
        for _ in range(5):
            controller.update(th.tensor(entropy))
        assert (temperature.alpha.item() - before) * direction > 0


def test_sgd_step_is_bounded_to_one_percent_of_alpha():
    temperature = EntropyTemperature(2.0)
    controller = TemperatureController(temperature, target=0.0, optimizer="sgd", learning_rate=1.0)
    gradient = controller.update(th.tensor(3.0))
    assert gradient == pytest.approx(3.0)  # d/d alpha of alpha * (H - H*)
    assert temperature.alpha.item() == pytest.approx(2.0 - 0.01 * 2.0)


@pytest.mark.parametrize("log_space", [False, True])
@pytest.mark.parametrize("optimizer, learning_rate", [("adam", 1e-3), ("adam", 0.1), ("sgd", 10.0)])
def test_every_update_moves_alpha_by_at_most_one_percent(optimizer, learning_rate, log_space):
    """The bound holds on the step, whatever the optimiser makes of the gradient: Adam's steps are
    about its learning rate in absolute terms, far beyond 1 % of a small alpha."""
    temperature = EntropyTemperature(0.05, log_space=log_space)
    controller = TemperatureController(
        temperature, target=0.5, optimizer=optimizer, learning_rate=learning_rate
    )
    alphas = [temperature.alpha.item()]
    for entropy in [1.0] * 50 + [0.0] * 50:
        controller.update(th.tensor(entropy))
        alphas.append(temperature.alpha.item())
    ratios = th.tensor(alphas[1:]) / th.tensor(alphas[:-1])
    assert ratios.min() >= 0.99 - 1e-6 and ratios.max() <= 1.01 + 1e-6
    assert alphas[50] < alphas[0] and alphas[100] > alphas[50]


@pytest.mark.parametrize("log_space", [False, True])
def test_adam_cannot_collapse_alpha_while_the_entropy_is_near_target(log_space):
    """300 updates with the entropy a little above target (0.52-0.53 against 0.5) leave alpha within
    0.99^300 of where it started, far above its floor (Adam's unbounded steps of about 1e-3 took alpha
    from 0.1 to the floor within about 100 updates)."""
    temperature = EntropyTemperature(0.1, log_space=log_space)
    controller = TemperatureController(temperature, target=0.5, optimizer="adam", learning_rate=1e-3)
    generator = th.Generator().manual_seed(0)
    for _ in range(300):
        controller.update(0.52 + 0.01 * th.rand(1, generator=generator))
    assert temperature.alpha.item() >= 0.1 * 0.99**300 > 100 * controller.min_alpha


def test_alpha_stays_above_its_floor():
    temperature = EntropyTemperature(1e-5)
    controller = TemperatureController(
        temperature, target=0.0, optimizer="sgd", learning_rate=10.0, max_step_ratio=0.5
    )
    controller.update(th.tensor(5.0))
    assert temperature.alpha.item() == pytest.approx(1e-5)


@pytest.mark.parametrize("log_space", [False, True])
@pytest.mark.parametrize("optimizer, learning_rate", [("adam", 1e-3), ("sgd", 0.1)])
def test_an_absent_group_keeps_its_alpha_and_optimiser_state(optimizer, learning_rate, log_space):
    """Group 1 is present for 20 updates (entropy above target: its alpha falls), then absent for 5:
    Adam's momentum must not move it on (it did, from 0.0951 to 0.0917 in 5 updates). Group 0 is
    present throughout and keeps moving."""
    temperature = EntropyTemperature(0.1, log_space=log_space, n_groups=2)
    controller = TemperatureController(
        temperature, target=th.tensor([0.5, 0.5]), optimizer=optimizer, learning_rate=learning_rate
    )
    if optimizer == "sgd":
        controller.optimizer.param_groups[0]["momentum"] = 0.9
    for _ in range(20):
        controller.update(th.tensor([1.0, 1.0]))
    alpha = temperature.alpha.detach().clone()
    state = {name: value.clone() for name, value in controller.optimizer.state[temperature.param].items()}
    for _ in range(5):
        controller.update(th.tensor([1.0, float("nan")]))
    assert temperature.alpha[1].item() == alpha[1].item() and temperature.alpha[0].item() < alpha[0].item()
    after = controller.optimizer.state[temperature.param]
    for name in ("exp_avg", "exp_avg_sq") if optimizer == "adam" else ("momentum_buffer",):
        assert (
            after[name][1].item() == state[name][1].item() and after[name][0].item() != state[name][0].item()
        )
    controller.update(th.tensor([1.0, 1.0]))  # present again: it moves on from where it stood
    assert temperature.alpha[1].item() < alpha[1].item()


def test_bad_temperature_arguments():
    with pytest.raises(ValueError, match="initial_alpha"):
        EntropyTemperature(0.0)
    with pytest.raises(ValueError, match="alpha_optimizer"):
        TemperatureController(EntropyTemperature(), 0.1, optimizer="rmsprop")
    with pytest.raises(ValueError, match="max_step_ratio"):
        TemperatureController(EntropyTemperature(), 0.1, max_step_ratio=1.0)


def test_auto_alpha_is_a_tenth_of_the_rewards_spread():
    rewards = np.array([0.0, 0.2, -0.2, 0.0], dtype=np.float32)
    assert alpha_from_rewards(rewards) == pytest.approx(0.1 * rewards.astype(np.float64).std())
    assert alpha_from_rewards(100 * rewards) == pytest.approx(100 * alpha_from_rewards(rewards))
    for constant in (np.full(1000, -0.01, np.float32), np.zeros(5), np.zeros(0)):
        assert alpha_from_rewards(constant) == FALLBACK_ALPHA  # float rounding is no spread


def tag_env_with_rewards_times(factor: float) -> TagEnv:
    """The tagging task with its rewards multiplied by ``factor``."""
    env = TagEnv(4, n_actions=9, p_target=0.5, penalty=0.5)
    step = env.step_arrays
    env.step_arrays = lambda actions: (lambda o, r, te, tr, i: (o, r * factor, te, tr, i))(*step(actions))
    return env


def small_rewards_tag_env() -> TagEnv:
    """The tagging task with rewards 100 times smaller: the values' differences are about 0.001."""
    return tag_env_with_rewards_times(0.01)


def large_rewards_tag_env() -> TagEnv:
    """The tagging task with rewards 100 times larger: discounted returns of order 100."""
    return tag_env_with_rewards_times(100.0)


@pytest.mark.parametrize("algorithm", [SoftHGRN, SACHGRN])
def test_auto_alpha_starts_at_the_first_gradient_step_from_the_stored_rewards(algorithm, tmp_path):
    from sb3_hgrn import make_graph_vec_env

    env = make_graph_vec_env(small_rewards_tag_env, n_envs=2, seed=0)
    small = dict(learning_starts=64, batch_size=4, train_freq=1, policy_kwargs=dict(hidden_dim=8, n_heads=1))
    model = algorithm("GraphPolicy", env, alpha_init="auto", learn_alpha=False, seed=0, **small)
    assert model.policy.temperature.alpha.item() == pytest.approx(FALLBACK_ALPHA)
    model.learn(64 + 8)
    stored = model.replay_buffer.rewards[: model.replay_buffer.pos]
    assert model.policy.temperature.alpha.item() == pytest.approx(alpha_from_rewards(stored), rel=1e-5)
    assert model.policy.temperature.alpha.item() < 0.01  # a fixed start of 0.1 is 10 times too hot here
    model.save(tmp_path / "model")
    loaded = algorithm.load(tmp_path / "model", env=env)
    loaded.replay_buffer.rewards[:] *= 1000  # other rewards: a resumed model must not start again
    loaded.learn(16, reset_num_timesteps=False)
    assert loaded.policy.temperature.alpha.item() == model.policy.temperature.alpha.item()


@pytest.mark.parametrize("algorithm", [SoftDQN, DiscreteSAC])
def test_auto_alpha_of_the_single_agent_classes(algorithm):
    model = algorithm(
        "MlpPolicy", "CartPole-v1", alpha_init="auto", learn_alpha=False, learning_starts=50, seed=0
    )
    model.learn(60)  # CartPole's reward is always 1: no spread, the fallback
    assert model.policy.temperature.alpha.item() == pytest.approx(FALLBACK_ALPHA)


@pytest.mark.parametrize("alpha_init", [0.0, -1.0, "automatic", True])
def test_bad_alpha_init_is_named(alpha_init):
    with pytest.raises(ValueError, match="alpha_init"):
        SoftHGRN("GraphPolicy", bit_vec_env(), alpha_init=alpha_init)


@pytest.mark.parametrize("algorithm", [SoftHGRN, SACHGRN])
def test_alpha_max_step_bounds_every_update_of_the_algorithms(algorithm, tmp_path):
    env = bit_vec_env()
    small = dict(learning_starts=8, batch_size=2, train_freq=1, policy_kwargs=dict(hidden_dim=8, n_heads=1))
    model = algorithm(
        "GraphPolicy",
        env,
        alpha_max_step=0.05,
        alpha_learning_rate=10.0,
        alpha_optimizer="sgd",
        seed=0,
        **small,
    )
    alphas = []
    model.learn(16 * 8, callback=lambda *_: alphas.append(model.policy.temperature.alpha.item()) or True)
    ratios = np.array(alphas[1:]) / np.array(alphas[:-1])
    moved = ratios[ratios != 1.0]
    assert moved.size and np.allclose(np.abs(moved - 1.0), 0.05, rtol=1e-4)  # the bound, not the default 1 %
    model.save(tmp_path / "model")
    assert algorithm.load(tmp_path / "model", env=env).temperature.max_step_ratio == 0.05
    with pytest.raises(ValueError, match="alpha_max_step"):
        algorithm("GraphPolicy", env, alpha_max_step=1.0)


@pytest.mark.parametrize("algorithm", [SoftHGRN, SACHGRN])
def test_a_model_saved_before_reward_scale_existed_loads_with_the_scale_it_trained_with(algorithm, tmp_path):
    from sb3_hgrn import make_graph_vec_env

    env = make_graph_vec_env(large_rewards_tag_env, n_envs=2, seed=0)
    model = algorithm("GraphPolicy", env, seed=0, policy_kwargs=dict(hidden_dim=8, n_heads=1))
    assert model.reward_scale == "auto"  # today's default
    model.save(tmp_path / "model")
    assert algorithm.load(tmp_path / "model").reward_scale == "auto"
    del model.reward_scale
    model.save(tmp_path / "earlier")  # as the models saved before the option: the env's own rewards
    assert algorithm.load(tmp_path / "earlier").reward_scale == 1.0
    assert algorithm.load(tmp_path / "earlier", reward_scale=2.0).reward_scale == 2.0


@pytest.mark.parametrize("algorithm", [SoftHGRN, SACHGRN])
def test_auto_reward_scale_is_measured_once_and_scales_every_target(algorithm, tmp_path):
    """``reward_scale="auto"`` becomes one over the stored returns' root mean square at the first
    gradient step (1 where that is below 1), a resumed model keeps it, and the targets' rewards are
    the stored ones times it."""
    from sb3_hgrn import make_graph_vec_env

    env = make_graph_vec_env(large_rewards_tag_env, n_envs=2, seed=0)
    small = dict(learning_starts=64, batch_size=4, train_freq=1, policy_kwargs=dict(hidden_dim=8, n_heads=1))
    model = algorithm("GraphPolicy", env, reward_scale="auto", seed=0, **small)
    assert model.applied_reward_scale == 1.0
    start, held = model._start_training, []
    model._start_training = lambda: (held.append(model.replay_buffer.return_rms(model.gamma)), start())
    model.learn(64 + 24)
    del model._start_training
    buffer = model.replay_buffer
    assert len(held) > 1 and model.applied_reward_scale == pytest.approx(1 / held[0], rel=1e-5)
    assert model.applied_reward_scale < 0.1  # rewards of 100 here
    np.random.seed(1)
    batch, steps = model._sample_runs(64)
    np.random.seed(1)
    stored = buffer.sample(64)
    assert stored.rewards.abs().sum() > 0
    th.testing.assert_close(batch.rewards, stored.rewards * model.applied_reward_scale)
    model.save(tmp_path / "model")
    loaded = algorithm.load(tmp_path / "model", env=env)
    loaded.replay_buffer.rewards[:] *= 1000
    loaded.learn(8, reset_num_timesteps=False)
    assert loaded.applied_reward_scale == model.applied_reward_scale
    small_env = make_graph_vec_env(small_rewards_tag_env, n_envs=2, seed=0)
    unscaled = algorithm("GraphPolicy", small_env, reward_scale="auto", seed=0, **small).learn(64 + 8)
    assert unscaled.replay_buffer.return_rms(unscaled.gamma) < 1 and unscaled.applied_reward_scale == 1.0
    for bad in (0, -1.0, float("nan"), "big"):
        with pytest.raises(ValueError, match="reward_scale must be a finite number > 0"):
            algorithm("GraphPolicy", env, reward_scale=bad, **small)
