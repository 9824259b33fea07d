"""SoftDQN and DiscreteSAC on single-agent Gymnasium envs: learning, save/load, observation kinds,
SB3's tooling and bad input."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.evaluation import evaluate_policy

from sb3_hgrn import DiscreteSAC, SoftDQN
from sb3_hgrn.cli import main
from sb3_hgrn.common import single_agent
from sb3_hgrn.common.soft_math import q_regression_loss, sac_next_value, soft_value
from sb3_hgrn.soft_dqn import soft_dqn
from tests.toy_envs import prefer_action

ALGORITHMS = {"SoftDQN": SoftDQN, "DiscreteSAC": DiscreteSAC}
SMALL = dict(
    learning_starts=16, batch_size=8, buffer_size=500, train_freq=4, policy_kwargs=dict(net_arch=[16])
)

ZOO_SCHEDULE = dict(
    learning_rate=2.3e-3, batch_size=64, learning_starts=1000, train_freq=256, gradient_steps=128, n_steps=3,
    target_entropy_ratio=0.05, policy_kwargs=dict(net_arch=[64, 64]),
)  # fmt: skip
"""The RL Zoo's DQN schedule for CartPole-v1 with 3-step returns and smaller networks."""
CARTPOLE = {
    "SoftDQN": dict(ZOO_SCHEDULE, target_update_interval=10),  # env steps: a copy per round
    "DiscreteSAC": dict(ZOO_SCHEDULE, tau=1.0, target_update_interval=128),  # gradient steps: likewise
}
"""Settings for CartPole-v1 (docs/single_agent.md has the returns of other seeds)."""
CARTPOLE_STEPS = 50_000
"""The Zoo's budget in env steps: the test's seed reaches 414.7 (SoftDQN) and 495.0 (DiscreteSAC)."""
CARTPOLE_CHECK_FREQ = 5_120
"""Env steps between the greedy checks that stop a CartPole run once it has learned (20 rounds)."""


def cartpole_greedy_return(model) -> float:
    """Mean greedy return of ``model`` over the same 10 CartPole-v1 episodes (env seeded 1000)."""
    env = gym.make("CartPole-v1")
    env.reset(seed=1000)
    mean_return, _ = evaluate_policy(model, env, n_eval_episodes=10, deterministic=True)
    return mean_return


class StopOnceLearned(BaseCallback):
    """Stops training at the first check (every ``check_freq`` env steps) where the greedy return over the
    test's episodes reaches ``threshold``: SB3's ``StopTrainingOnRewardThreshold`` on fixed episodes."""

    def __init__(self, check_freq: int, threshold: float):
        super().__init__()
        self.check_freq = check_freq
        self.threshold = threshold

    def _on_step(self) -> bool:
        if self.num_timesteps % self.check_freq:
            return True
        return cartpole_greedy_return(self.model) < self.threshold


class DictObservation(gym.ObservationWrapper):
    """CartPole with its observation split into a dict of two Boxes."""

    def __init__(self, env: gym.Env):
        super().__init__(env)
        self.observation_space = gym.spaces.Dict(
            {
                "position": gym.spaces.Box(-np.inf, np.inf, (2,)),
                "velocity": gym.spaces.Box(-np.inf, np.inf, (2,)),
            }
        )

    def observation(self, observation: np.ndarray) -> dict[str, np.ndarray]:
        return {"position": observation[[0, 2]], "velocity": observation[[1, 3]]}


class ImageEnv(gym.Env):
    """36 x 36 one-channel images (the smallest NatureCNN takes); reward 1 for the action that
    matches the image's brightness, 8-step episodes."""

    observation_space = gym.spaces.Box(0, 255, (36, 36, 1), dtype=np.uint8)
    action_space = gym.spaces.Discrete(2)

    def reset(self, seed=None, options=None):
        super().reset(seed=seed)
        self._t = 0
        return self._draw(), {}

    def _draw(self) -> np.ndarray:
        self._bright = int(self.np_random.integers(2))
        return np.full((36, 36, 1), 200 * self._bright, dtype=np.uint8)

    def step(self, action):
        reward = float(action == self._bright)
        self._t += 1
        return self._draw(), reward, False, self._t >= 8, {}


class ContinuousEnv(gym.Env):
    observation_space = gym.spaces.Box(-1, 1, (2,))
    action_space = gym.spaces.Box(-1, 1, (1,))


class MultiDiscreteEnv(ContinuousEnv):
    action_space = gym.spaces.MultiDiscrete([2, 3])


@pytest.mark.parametrize("name", ALGORITHMS)
def test_learns_cartpole(name):
    model = ALGORITHMS[name]("MlpPolicy", "CartPole-v1", seed=0, **CARTPOLE[name])
    model.learn(CARTPOLE_STEPS, callback=StopOnceLearned(CARTPOLE_CHECK_FREQ, threshold=400))
    assert cartpole_greedy_return(model) >= 400


@pytest.mark.parametrize("name", ALGORITHMS)
def test_save_load_gives_identical_predictions(name, tmp_path):
    model = ALGORITHMS[name]("MlpPolicy", "CartPole-v1", seed=1, **SMALL).learn(200)
    observations = np.random.default_rng(0).normal(size=(32, 4)).astype(np.float32)
    model.save(tmp_path / "model.zip")
    loaded = ALGORITHMS[name].load(tmp_path / "model.zip")
    for deterministic in (True, False):
        th.manual_seed(3)
        expected, _ = model.predict(observations, deterministic=deterministic)
        th.manual_seed(3)
        actual, _ = loaded.predict(observations, deterministic=deterministic)
        np.testing.assert_array_equal(actual, expected)
    assert loaded.policy.temperature.alpha.item() == model.policy.temperature.alpha.item()
    assert (
        loaded.temperature.optimizer.state_dict()["state"].keys()
        == model.temperature.optimizer.state_dict()["state"].keys()
    )


@pytest.mark.parametrize("name", ALGORITHMS)
def test_adam_is_fused_by_default_and_models_saved_unfused_learn_on(name, tmp_path, monkeypatch):
    assert ALGORITHMS[name]("MlpPolicy", "CartPole-v1", **SMALL).policy.optimizer_kwargs == {"fused": True}
    with monkeypatch.context() as patch:  # a model saved before Adam was fused by default
        patch.setattr(single_agent, "fused_by_default", lambda _, kwargs: dict(kwargs or {}))
        earlier = ALGORITHMS[name]("MlpPolicy", "CartPole-v1", seed=1, **SMALL).learn(200)
        assert earlier.policy.optimizer_kwargs == {}
        earlier.save(tmp_path / "earlier.zip")
    loaded = ALGORITHMS[name].load(tmp_path / "earlier.zip", env=gym.make("CartPole-v1"))
    assert loaded.policy.optimizer_kwargs == {"fused": True}
    before = [p.detach().clone() for p in loaded.policy.parameters()]
    loaded.learn(200, reset_num_timesteps=False)
    after = list(loaded.policy.parameters())
    assert all(th.isfinite(p).all() for p in after)
    assert any(not th.equal(b, a) for b, a in zip(before, after, strict=True))


def test_discrete_sac_load_refuses_a_behaviour_policy_the_saved_policy_does_not_act_with(tmp_path):
    DiscreteSAC("MlpPolicy", "CartPole-v1", **SMALL).save(tmp_path / "model")
    assert DiscreteSAC.load(tmp_path / "model", behaviour_policy="actor").policy.behaviour_policy == "actor"
    with pytest.raises(ValueError, match="built with behaviour_policy='actor'; load cannot change it"):
        DiscreteSAC.load(tmp_path / "model", behaviour_policy="critic")
    options = dict(behaviour_policy="critic", critic_target="boltzmann", actor_steps=0)
    DiscreteSAC("MlpPolicy", "CartPole-v1", **SMALL, **options).save(tmp_path / "no_actor")
    with pytest.raises(
        ValueError, match="actor_steps=0 leaves the actor untrained, but critic_target='actor'"
    ):
        DiscreteSAC.load(tmp_path / "no_actor", critic_target="actor")


@pytest.mark.parametrize("name", ALGORITHMS)
@pytest.mark.parametrize(
    "policy, make_env",
    [
        ("MlpPolicy", lambda: gym.make("CartPole-v1")),
        ("MultiInputPolicy", lambda: DictObservation(gym.make("CartPole-v1"))),
        ("CnnPolicy", ImageEnv),
    ],
    ids=["box", "dict", "image"],
)
def test_trains_and_acts_on_every_observation_kind(name, policy, make_env):
    env = make_vec_env(make_env, n_envs=2, seed=0)
    options = {**SMALL, "policy_kwargs": {}} if policy == "CnnPolicy" else SMALL
    model = ALGORITHMS[name](policy, env, seed=0, **options).learn(80)
    assert model._n_updates > 0
    actions, _ = model.predict(env.reset(), deterministic=False)
    assert actions.shape == (2,) and env.action_space.contains(int(actions[0]))
    evaluate_policy(model, env, n_eval_episodes=2)


@pytest.mark.parametrize("name", ALGORITHMS)
def test_logs_the_temperature_and_calls_callbacks(name, tmp_path):
    class Count(BaseCallback):
        calls = 0

        def _on_step(self) -> bool:
            Count.calls += 1
            return True

    model = ALGORITHMS[name]("MlpPolicy", "CartPole-v1", seed=0, tensorboard_log=str(tmp_path), **SMALL)
    model.learn(100, callback=Count())
    assert Count.calls == 100
    figures = model.logger.name_to_value
    assert {"train/alpha", "train/entropy", "train/target_entropy", "train/alpha_grad"} <= set(figures)
    assert figures["train/target_entropy"] == pytest.approx(0.2 * np.log(2))
    assert (tmp_path / f"{name}_1").is_dir()


def test_n_step_targets_and_learned_temperature_move_alpha():
    model = SoftDQN("MlpPolicy", "CartPole-v1", seed=0, n_steps=3, **SMALL).learn(200)
    assert model.policy.temperature.alpha.item() != pytest.approx(0.1)
    model = DiscreteSAC("MlpPolicy", "CartPole-v1", seed=0, learn_alpha=False, **SMALL).learn(200)
    assert model.policy.temperature.alpha.item() == pytest.approx(0.1)


def test_targets_are_the_shared_soft_values():
    model = SoftDQN("MlpPolicy", "CartPole-v1", seed=0, **SMALL)
    q = th.tensor([[1.0, 3.0]])
    alpha = model.policy.temperature.per_agent(None)
    assert soft_value(q, alpha).item() == pytest.approx(0.1 * np.log(np.exp(10) + np.exp(30)), rel=1e-6)
    logits = th.tensor([[0.0, np.log(3.0)]])
    expected = 0.25 * (1.0 - 0.1 * np.log(0.25)) + 0.75 * (3.0 - 0.1 * np.log(0.75))
    assert sac_next_value(q, logits, alpha).item() == pytest.approx(expected, rel=1e-6)


def test_boltzmann_critic_targets_average_over_the_critics_policy_without_the_actor():
    """With ``critic_target="boltzmann"`` the next value is the soft expectation over
    ``softmax(Q / alpha)``, which is the soft value, and the actor is not run for it."""
    q = th.tensor([[1.0, 3.0, -2.0], [0.5, 0.0, 0.2]])
    alpha = th.tensor([0.7])

    def unused_actor() -> th.Tensor:
        raise AssertionError("the actor ran for a Boltzmann target")

    model = DiscreteSAC("MlpPolicy", "CartPole-v1", critic_target="boltzmann")
    boltzmann = model._next_value(q, unused_actor, alpha)
    assert th.allclose(boltzmann, sac_next_value(q, q / alpha, alpha))
    assert th.allclose(boltzmann, soft_value(q, alpha))
    model.critic_target = "actor"
    uniform_actor = th.zeros_like(q)
    assert th.allclose(
        model._next_value(q, lambda: uniform_actor, alpha), sac_next_value(q, uniform_actor, alpha)
    )


@pytest.mark.parametrize("name", ALGORITHMS)
@pytest.mark.parametrize("env_class, kind", [(ContinuousEnv, "Box"), (MultiDiscreteEnv, "MultiDiscrete")])
def test_rejects_action_spaces_other_than_discrete(name, env_class, kind):
    with pytest.raises(TypeError, match=f"{name} needs an env with a Discrete action space, got {kind}"):
        ALGORITHMS[name]("MlpPolicy", env_class())


@pytest.mark.parametrize(
    "options, message",
    [
        (dict(actor_loss="mse"), "actor_loss must be one of"),
        (dict(alpha_entropy="critic"), "alpha_entropy must be one of"),
        (dict(actor_steps=-1), "actor_steps must be an integer >= 0 or .auto., got -1"),
        (dict(actor_steps=0), "actor_steps=0 leaves the actor untrained, but behaviour_policy='actor'"),
        (dict(policy_kwargs=dict(n_critics=0)), "n_critics must be a positive integer, got 0"),
        (dict(behaviour_policy="target"), "behaviour_policy must be one of"),
        (dict(critic_target="critic"), "critic_target must be one of"),
        (
            dict(behaviour_policy="critic", policy_kwargs=dict(behaviour_policy="actor")),
            "policy_kwargs.behaviour_policy='actor' disagrees",
        ),
    ],
)
def test_discrete_sac_names_bad_options(options, message):
    with pytest.raises(ValueError, match=message):
        DiscreteSAC("MlpPolicy", "CartPole-v1", **options)


def test_q_regression_losses():
    """Squared error, or Huber's (half the square up to 1, then linear), over the masked entries."""
    q_values = th.tensor([[1.0, 2.0], [0.0, 4.0], [7.0, 7.0]])
    actions = th.tensor([[1], [1], [0]])
    target, mask = th.tensor([1.5, 1.0, 0.0]), th.tensor([1.0, 1.0, 0.0])  # errors 0.5, 3 (and 7 masked)
    assert q_regression_loss(q_values, actions, target, mask).item() == pytest.approx((0.25 + 9.0) / 2)
    huber = q_regression_loss(q_values, actions, target, mask, "huber").item()
    assert huber == pytest.approx((0.125 + 2.5) / 2)


def test_soft_dqn_regresses_with_its_q_loss(monkeypatch):
    used = []

    def recording_loss(*args):
        used.append(args[-1])
        return q_regression_loss(*args)

    monkeypatch.setattr(soft_dqn, "q_regression_loss", recording_loss)
    SoftDQN("MlpPolicy", "CartPole-v1", q_loss="huber", learning_starts=32, seed=0).learn(64)
    assert used and set(used) == {"huber"}
    with pytest.raises(ValueError, match="q_loss must be one of 'mse', 'huber', got 'l1'"):
        SoftDQN("MlpPolicy", "CartPole-v1", q_loss="l1")


@pytest.mark.parametrize("behaviour_policy, preferred", [("actor", 0), ("critic", 1)])
def test_discrete_sac_collects_and_deploys_its_behaviour_policy(behaviour_policy, preferred, tmp_path):
    """The actor, or the first critic's Boltzmann policy, collects and is what ``predict`` acts
    with, before and after a save and load."""
    options = {**SMALL, "learning_starts": 0, "gradient_steps": 0, "behaviour_policy": behaviour_policy}
    model = DiscreteSAC("MlpPolicy", "CartPole-v1", seed=0, **options)
    model.policy.temperature.reset(0.5)
    prefer_action(model.policy.actor, 0)
    prefer_action(model.policy.critics[0], 1)
    model.learn(200)
    stored = model.replay_buffer.actions[: model.replay_buffer.pos]
    assert (stored == preferred).mean() > 0.99  # the other action has probability e^-20
    observations = np.random.default_rng(0).normal(size=(32, 4)).astype(np.float32)
    assert (model.predict(observations)[0] == preferred).all()
    model.save(tmp_path / "model.zip")
    loaded = DiscreteSAC.load(tmp_path / "model.zip")
    assert loaded.behaviour_policy == loaded.policy.behaviour_policy == behaviour_policy
    assert (loaded.predict(observations)[0] == preferred).all()


def test_cli_trains_a_single_agent_preset(tmp_path, capsys):
    arguments = ["train", "--env", "CartPole-v1", "--preset", "soft_dqn", "--folder", str(tmp_path)]
    small = ["--timesteps", "300", "--verbose", "0", "--param", "learning_starts=50", "buffer_size=1000"]
    assert main([*arguments, *small]) == 0
    folder = tmp_path / "CartPole-v1" / "soft_dqn" / "seed_0"
    assert (folder / "model.zip").is_file() and (folder / "eval.json").is_file()
    SoftDQN.load(folder / "model.zip")
    assert "soft_dqn on CartPole-v1 (seed 0): return" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        main([*arguments, *small])
    assert "holds a finished run (eval.json); pass --overwrite" in capsys.readouterr().err


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--env", "Pendulum-v1"], "hyperparams/soft_dqn.yml have no settings for the env 'Pendulum-v1'"),
        (
            ["--env", "CartPole-v1", "--param", "policy_kwargs.features_extractor_class=Resnet"],
            "CartPole-v1.policy_kwargs.features_extractor_class 'Resnet' is not one of NatureCNN",
        ),
        (["--env", "CartPole-v1", "--param", "n_timesteps=0"], "CartPole-v1.n_timesteps must be a positive"),
        (["--env", "CartPole-v1", "--config", "no_such_file.yml"], "Cannot read the hyperparameter file"),
        (["--env", "CartPole-v1", "--budget", "ci"], "--budget applies to graph envs"),
        (["--env", "CartPole-v1", "--param", "no_such_option=1"], "Cannot build SoftDQN on CartPole-v1"),
    ],
)
def test_cli_names_bad_single_agent_input(extra, message, tmp_path, capsys):
    with pytest.raises(SystemExit):
        main(["train", "--preset", "soft_dqn", "--folder", str(tmp_path), *extra])
    assert message in capsys.readouterr().err


def test_an_env_id_of_a_plugin_package_is_registered_from_its_entry_point(monkeypatch):
    """Gymnasium 1.x no longer calls the ``gymnasium.envs`` entry points that plugin packages (as
    MinAtar) register their envs with; the single-agent classes and runs call the one named after
    the id's namespace, once, before making the env."""
    from types import SimpleNamespace

    from sb3_hgrn.envs import registration

    calls = []

    def register_toy_envs():
        calls.append("Toy")
        gym.register(id="Toy/Cartpole-v7", entry_point="gymnasium.envs.classic_control:CartPoleEnv")

    plugins = [SimpleNamespace(name="Other", load=lambda: pytest.fail("another namespace was loaded"))]
    plugins.append(SimpleNamespace(name="Toy", load=lambda: register_toy_envs))
    monkeypatch.setattr(registration, "entry_points", lambda group: plugins)
    try:
        model = SoftDQN("MlpPolicy", "Toy/Cartpole-v7", seed=0)
        assert model.env.observation_space.shape == (4,)
        assert registration.ensure_registered("Toy/Cartpole-v7") == "Toy/Cartpole-v7"
        assert calls == ["Toy"]  # registered once
        with pytest.raises(gym.error.NamespaceNotFound):
            SoftDQN("MlpPolicy", "Unknown/Game-v0")
    finally:
        gym.registry.pop("Toy/Cartpole-v7", None)
