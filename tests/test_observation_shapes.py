"""Observations of more than one dimension: flattened by default, or read by a features extractor."""

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from torch import nn

from sb3_hgrn import SACHGRN, AgentViewCNN, SoftHGRN, make_graph_vec_env
from sb3_hgrn.common.checks import observation_problem
from sb3_hgrn.common.hgrn import HGRN
from sb3_hgrn.envs.base import AgentGroup
from sb3_hgrn.presets import PRESETS, make_model
from tests.toy_envs import CornerViewEnv, SignalReaderEnv

ALGORITHMS = {"SoftHGRN": SoftHGRN, "SACHGRN": SACHGRN}
VIEW = (5, 5, 3)


class FlatLinearExtractor(BaseFeaturesExtractor):
    """``ReLU(Linear(flattened observation))``, remembering the input shapes it was called with."""

    def __init__(self, observation_space: gym.spaces.Box, features_dim: int = 8):
        super().__init__(observation_space, features_dim)
        self.linear = nn.Linear(int(np.prod(observation_space.shape)), features_dim)
        self.input_shapes: set[tuple[int, ...]] = set()

    def forward(self, observations: th.Tensor) -> th.Tensor:
        self.input_shapes.add(tuple(observations.shape[1:]))
        return th.relu(self.linear(observations.flatten(1)))


class TooNarrowExtractor(FlatLinearExtractor):
    """Declares ``features_dim`` but returns half as many features."""

    def forward(self, observations: th.Tensor) -> th.Tensor:
        return super().forward(observations)[:, : self.features_dim // 2]


def view_env(n_envs: int = 2, seed: int = 0):
    return make_graph_vec_env(lambda: CornerViewEnv(n_agents=4, size=VIEW[0]), n_envs=n_envs, seed=seed)


def small_model(algorithm: str, env, **policy_kwargs):
    return ALGORITHMS[algorithm](
        "GraphPolicy", env, learning_starts=64, batch_size=8, train_freq=1, buffer_size=2_000, seed=0,
        policy_kwargs=dict(hidden_dim=16, n_heads=2, **policy_kwargs),
    )  # fmt: skip


def networks(model) -> list[HGRN]:
    return [module for module in model.policy.modules() if isinstance(module, HGRN)]


def trained_networks(model) -> list[HGRN]:
    """The networks a gradient step updates (not the target copies, nor an actor that never trains:
    SACHGRN's at its defaults, ``actor_steps="auto"``)."""
    policy = model.policy
    if isinstance(model, SoftHGRN):
        return [policy.q_net]
    return [*([policy.actor] if model.actor_steps else []), *policy.critics]


def extractor_parameters(network: HGRN) -> list[th.Tensor]:
    return [parameter.detach().clone() for parameter in network.features_extractor.parameters()]


def test_env_keeps_the_view_shape_and_dtype():
    env = view_env()
    assert env.observation_space["obs"].shape == VIEW
    obs = env.reset()
    assert obs["obs"].shape == (env.num_envs, *VIEW) and obs["obs"].dtype == np.uint8
    assert obs["obs"].reshape(env.num_envs, -1)[:, 0::3].sum(axis=1).tolist() == [1] * env.num_envs


@pytest.mark.parametrize("algorithm", ALGORITHMS)
def test_trains_on_flattened_views(algorithm):
    model = small_model(algorithm, view_env())
    encoders = [network.encoder[0][0] for network in trained_networks(model)]
    before = [encoder.weight.detach().clone() for encoder in encoders]
    assert {encoder.in_features for encoder in encoders} == {int(np.prod(VIEW))}
    assert all(network.features_extractor is None for network in networks(model))
    model.learn(300)
    buffer = model.replay_buffer
    assert buffer.observations.shape[1:] == (2, 4, *VIEW) and buffer.observations.dtype == np.uint8
    stored = buffer.observations[: buffer.pos].reshape(-1, *VIEW)
    assert (stored[..., 0].reshape(len(stored), -1).sum(axis=1) == 1).all()  # one corner per view
    for encoder, weight in zip(encoders, before, strict=True):
        assert not th.equal(encoder.weight, weight)


@pytest.mark.parametrize("algorithm", ALGORITHMS)
def test_custom_extractor_feeds_every_network_and_learns(algorithm):
    model = small_model(
        algorithm,
        view_env(),
        features_extractor_class=FlatLinearExtractor,
        features_extractor_kwargs=dict(features_dim=6),
    )
    for network in networks(model):
        (extractor,) = network.features_extractor.members
        assert isinstance(extractor, FlatLinearExtractor) and extractor.features_dim == 6
        assert network.encoder[0][0].in_features == 6
    assert len({id(network.features_extractor[0]) for network in networks(model)}) == len(networks(model))
    before = [extractor_parameters(network) for network in trained_networks(model)]
    model.learn(300)
    for network, parameters in zip(trained_networks(model), before, strict=True):
        assert network.features_extractor[0].input_shapes == {VIEW}
        changed = [not th.equal(now, then) for now, then in zip(network.features_extractor.parameters(),
                                                                  parameters, strict=True)]  # fmt: skip
        assert all(changed)


def test_extractor_output_decides_the_networks_output():
    model = small_model("SoftHGRN", view_env(n_envs=1), features_extractor_class=FlatLinearExtractor)
    obs = model.env.reset()
    q_net = model.policy.q_net
    observations, neighbors, _ = model.policy.to_graphs(model.policy.obs_to_tensor(obs)[0])
    hidden = th.zeros(1, 4, q_net.state_dim)
    with th.no_grad():
        before, _ = q_net(observations, neighbors, hidden)
        q_net.features_extractor[0].linear.bias.add_(1.0)
        after, _ = q_net(observations, neighbors, hidden)
    assert not th.allclose(before, after)


@pytest.mark.parametrize("algorithm", ALGORITHMS)
def test_agent_view_cnn_trains_and_survives_save_load(algorithm, tmp_path):
    env = view_env()
    extractor_kwargs = dict(features_dim=8, channels=(4,))
    model = small_model(
        algorithm, env, features_extractor_class=AgentViewCNN, features_extractor_kwargs=extractor_kwargs
    )
    before = [extractor_parameters(network) for network in trained_networks(model)]
    model.learn(300)
    for network, parameters in zip(trained_networks(model), before, strict=True):
        assert all(
            not th.equal(now, then)
            for now, then in zip(network.features_extractor.parameters(), parameters, strict=True)
        )
    model.save(tmp_path / "model.zip")
    loaded = ALGORITHMS[algorithm].load(tmp_path / "model.zip", env=env)
    assert loaded.policy_kwargs["features_extractor_class"] is AgentViewCNN
    assert loaded.policy_kwargs["features_extractor_kwargs"] == extractor_kwargs
    assert all(isinstance(network.features_extractor[0], AgentViewCNN) for network in networks(loaded))
    obs = env.reset()
    starts = np.ones(env.num_envs, dtype=bool)
    states = [None, None]
    for _ in range(3):
        (actions, state), (loaded_actions, loaded_state) = (
            used.predict(obs, state=previous, episode_start=starts, deterministic=True)
            for used, previous in zip((model, loaded), states, strict=True)
        )
        np.testing.assert_array_equal(actions, loaded_actions)
        np.testing.assert_array_equal(state[0], loaded_state[0])
        assert np.abs(state[0]).sum() > 0
        states = [state, loaded_state]
        obs, _, starts, _ = env.step(actions)


def test_agent_view_cnn_reads_channel_last_views():
    space = gym.spaces.Box(0.0, 1.0, shape=(4, 6, 3), dtype=np.float32)
    cnn = AgentViewCNN(space, features_dim=5, channels=(2, 3))
    assert cnn.cnn[0].in_channels == 3 and cnn.linear[0].in_features == 3 * 4 * 6
    assert cnn(th.rand(7, 4, 6, 3)).shape == (7, 5)
    with pytest.raises(ValueError, match=r"channel-last views: a Box of shape \(height, width, channels\)"):
        AgentViewCNN(gym.spaces.Box(0.0, 1.0, shape=(12,)))


@pytest.mark.parametrize("preset", PRESETS)
def test_every_preset_honours_the_extractor(preset):
    model = make_model(
        preset,
        view_env(n_envs=1),
        buffer_size=1_000,
        policy_kwargs=dict(
            hidden_dim=8, n_heads=2, features_extractor_class=FlatLinearExtractor,
            features_extractor_kwargs=dict(features_dim=5),
        ),
    )  # fmt: skip
    found = networks(model)
    assert len(found) >= 2  # with the target copies
    for network in found:
        assert isinstance(network.features_extractor[0], FlatLinearExtractor)
        assert network.encoder[0][0].in_features == 5
    actions, _ = model.predict(model.env.reset())
    assert actions.shape == (4,)


def test_heterogeneous_groups_get_one_extractor_each():
    env = make_graph_vec_env(lambda: SignalReaderEnv(n_pairs=2), n_envs=2, seed=0)
    model = small_model("SACHGRN", env, features_extractor_class=FlatLinearExtractor)
    for network in networks(model):
        assert len(network.features_extractor.members) == 2
    extractors = [
        extractor for network in trained_networks(model) for extractor in network.features_extractor
    ]
    before = [
        [parameter.detach().clone() for parameter in extractor.parameters()] for extractor in extractors
    ]
    model.learn(300)
    for extractor, parameters in zip(extractors, before, strict=True):
        assert extractor.input_shapes == {(2,)}  # the padded shared observation
        assert any(
            not th.equal(now, then) for now, then in zip(extractor.parameters(), parameters, strict=True)
        )


def test_bad_extractors_are_refused_with_a_clear_error():
    with pytest.raises(ValueError, match=r"TooNarrowExtractor maps observations of shape \(2, 5, 5, 3\)"):
        small_model("SoftHGRN", view_env(), features_extractor_class=TooNarrowExtractor)
    with pytest.raises(ValueError, match=r"TooNarrowExtractor .* must return .* = \(2, 8\)"):
        small_model("SACHGRN", view_env(), features_extractor_class=TooNarrowExtractor)
    with pytest.raises(TypeError, match="needs a positive integer features_dim attribute"):
        small_model("SoftHGRN", view_env(), features_extractor_class=lambda space: nn.Flatten())
    flat_env = make_graph_vec_env(lambda: SignalReaderEnv(n_pairs=2), n_envs=1)
    with pytest.raises(ValueError, match="AgentViewCNN reads channel-last views"):
        small_model("SoftHGRN", flat_env, features_extractor_class=AgentViewCNN)


class TwoShapeEnv(CornerViewEnv):
    """:class:`CornerViewEnv` whose second group claims views of another shape."""

    def __init__(self):
        super().__init__(n_agents=4)
        view = self.shared_observation_space
        self.groups = (
            AgentGroup("a", view, self.shared_action_space),
            AgentGroup("b", gym.spaces.Box(0, 1, shape=(3, 3, 3), dtype=np.uint8), self.shared_action_space),
        )
        self.group_ids = np.array([0, 0, 1, 1])


def test_groups_of_views_must_share_their_shape():
    with pytest.raises(ValueError, match=r"Group 'b' observes shape \(3, 3, 3\).*every group must observe"):
        make_graph_vec_env(TwoShapeEnv)


def test_bad_view_values_are_named_by_their_index():
    space = gym.spaces.Box(0, 1, shape=VIEW, dtype=np.float32)
    obs = np.zeros((4, *VIEW), dtype=np.float32)
    obs[2, 1, 3, 2] = 7.0
    problem = observation_problem({"obs": obs, "neighbors": np.zeros((4, 1))}, space, 4)
    assert problem == (2, "the value 7.0 at obs index (1, 3, 2), outside the observation space [0.0, 1.0]")


def test_hgrn_names_the_observation_shape_it_needs():
    network = HGRN(obs_dim=VIEW, n_actions=4, hidden_dim=8)
    neighbors = th.zeros(1, 2, 1, dtype=th.long)
    out, _ = network(th.zeros(1, 2, *VIEW), neighbors, th.zeros(1, 2, 8))
    assert out.shape == (1, 2, 4)
    with pytest.raises(
        ValueError, match=r"obs must have shape \(batch, n_agents, 5, 5, 3\), got \(1, 2, 75\)"
    ):
        network(th.zeros(1, 2, 75), neighbors, th.zeros(1, 2, 8))
