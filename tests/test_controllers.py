"""ModelController: the learner-side wrapper that loads a model to drive one side of an env and seeds
its sampling from the env."""

import io
import json
import zipfile

import gymnasium as gym
import numpy as np
import pytest
import torch as th

from sb3_hgrn.common.saved_controllers import ModelController, load_controller


class TorchSampler:
    """A model whose actions are torch samples: ``(n_agents,)`` draws in ``0..8``."""

    observation_space = gym.spaces.Dict(
        {"obs": gym.spaces.Box(0, 1, (3,), dtype=np.uint8), "neighbors": gym.spaces.Box(-1, 9, (4,))}
    )

    def predict(self, observation, state=None, episode_start=None, deterministic=False):
        return th.randint(0, 9, (len(observation["obs"]),)).numpy(), state


OBSERVATION = {"obs": np.zeros((5, 3), dtype=np.uint8), "neighbors": np.full((5, 4), -1, dtype=np.int32)}


def test_a_seed_makes_the_next_prediction_repeat_and_leaves_the_callers_torch_state():
    controller = ModelController(TorchSampler())
    th.manual_seed(0)
    caller_state = th.random.get_rng_state()
    draws = []
    for _ in range(2):
        controller.seed(np.int64(7))
        draws.append(controller.predict(OBSERVATION)[0])
    np.testing.assert_array_equal(*draws)
    assert th.equal(th.random.get_rng_state(), caller_state)
    unseeded = controller.predict(OBSERVATION)[0]  # a seed holds for one call: this one is the caller's
    th.manual_seed(0)
    np.testing.assert_array_equal(unseeded, th.randint(0, 9, (5,)).numpy())


def test_bind_refuses_a_model_of_other_observations():
    controller = ModelController(TorchSampler())
    controller.bind(gym.spaces.Box(0, 1, (3,), dtype=np.uint8), 5)
    with pytest.raises(ValueError, match=r"takes observations of shape \(3,\), but the 5 agents .* \(4,\)"):
        controller.bind(gym.spaces.Box(0, 1, (4,), dtype=np.uint8), 5)


def test_what_is_no_model_is_refused(tmp_path):
    with pytest.raises(TypeError, match="a model with predict\\(\\) or a saved model's path, got int"):
        ModelController(3)
    with pytest.raises(ValueError, match=r"No saved model at .*missing \(nor .*missing.zip\)"):
        ModelController(tmp_path / "missing")
    weights = io.BytesIO()
    th.save({}, weights)
    with zipfile.ZipFile(tmp_path / "dqn.zip", "w") as archive:
        archive.writestr(
            "data", json.dumps({"policy_class": {"__module__": "stable_baselines3.dqn.policies"}})
        )
        archive.writestr("policy.pth", weights.getvalue())
    with pytest.raises(
        ValueError, match="dqn.zip is not an sb3_hgrn model: it was saved by stable_baselines3's DQN"
    ):
        load_controller(tmp_path / "dqn")
