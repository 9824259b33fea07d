import math
import os

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3.common.callbacks import CheckpointCallback, EvalCallback
from stable_baselines3.common.vec_env import DummyVecEnv

from sb3_hgrn import (
    SACHGRN,
    GraphEvalCallback,
    RandomGraphPolicy,
    SoftHGRN,
    evaluate_graph_policy,
    make_graph_vec_env,
)
from sb3_hgrn.common import policies as graph_policies
from sb3_hgrn.common.soft_math import soft_value
from tests.doc_snippets import docstring_example, python_block, run_snippet
from tests.toy_envs import DictOnlyEnv, NeighborBitEnv, check_deployed_average
from tests.toy_envs import bit_vec_env as bit_env

SMALL = dict(hidden_dim=16, n_heads=2)


def quick_model(env, **kwargs):
    options = dict(learning_starts=64, batch_size=8, train_freq=1, policy_kwargs=SMALL, seed=0)
    options.update(kwargs)
    return SoftHGRN("GraphPolicy", env, **options)


def test_learns_the_neighbour_bit_task_only_with_communication():
    """Copying the left neighbour's bit scores 1 per agent-step (32 per team episode); an agent
    without communication cannot beat chance (16)."""
    returns = {}
    for communication in ("hgat", "none"):
        model = quick_model(
            bit_env(), learning_starts=256, batch_size=16, target_entropy_ratio=0.05,
            policy_kwargs=dict(hidden_dim=32, communication=communication),
        )  # fmt: skip
        model.learn(12_000)
        returns[communication], _ = evaluate_graph_policy(model, bit_env(seed=100), n_eval_episodes=16)
    assert returns["hgat"] >= 29.0
    assert returns["none"] <= 20.0


def test_learns_the_neighbour_bit_task_with_mixed_precision(tmp_path):
    model = quick_model(
        bit_env(), learning_starts=256, batch_size=16, target_entropy_ratio=0.05,
        policy_kwargs=dict(hidden_dim=32, mixed_precision=True),
    )  # fmt: skip
    model.learn(12_000)
    mean_return, _ = evaluate_graph_policy(model, bit_env(seed=100), n_eval_episodes=16)
    assert mean_return >= 29.0
    model.save(tmp_path / "model.zip")
    loaded = SoftHGRN.load(tmp_path / "model.zip", env=bit_env())
    assert loaded.policy.q_net.mixed_precision and loaded.policy.network_kwargs["mixed_precision"]


def test_predict_threads_recurrent_state_like_recurrent_ppo():
    env = bit_env(n_envs=2)
    model = quick_model(env)
    obs = env.reset()
    actions, state = model.predict(obs)
    assert actions.shape == (8,) and isinstance(state, tuple) and state[0].shape == (1, 8, 16)
    assert np.abs(state[0]).sum() > 0
    _, next_state = model.predict(obs, state=state, episode_start=np.zeros(8, dtype=bool))
    _, reset_state = model.predict(obs, state=state, episode_start=np.ones(8, dtype=bool))
    _, fresh_state = model.predict(obs)
    np.testing.assert_allclose(reset_state[0], fresh_state[0])
    assert not np.allclose(next_state[0], fresh_state[0])


@pytest.mark.parametrize("algorithm", [SoftHGRN, SACHGRN])
def test_predict_acts_in_evaluation_mode_however_training_mode_was_set(algorithm):
    """predict() switches to evaluation mode when the policy, or only its deployed network, was left
    in training mode (a features extractor with dropout would act differently)."""
    env = bit_env()
    model = algorithm("GraphPolicy", env, learning_starts=64, batch_size=8, policy_kwargs=SMALL, seed=0)
    obs = env.reset()
    policy = model.policy
    policy.set_training_mode(True)
    model.predict(obs)
    assert not policy.training and not policy.deployed_network.training
    policy.deployed_network.train(True)  # only the network, behind the policy's back
    model.predict(obs)
    assert not any(module.training for module in policy.deployed_network.modules())


def test_hidden_state_is_threaded_and_stored_during_warm_up():
    env = bit_env(n_envs=2)
    model = quick_model(env, learning_starts=10_000)
    model.learn(8 * 20)
    buffer = model.replay_buffer
    assert buffer.pos == 20 and model._n_updates == 0
    # the state carried into step t is produced by step t-1, so it is non-zero inside episodes
    inside = ~buffer.episode_starts[:20, 0]
    assert np.abs(buffer.hidden[:20][inside].astype(np.float32)).sum() > 0
    assert buffer.episode_starts[0].all() and buffer.episode_starts[8].all()
    assert not buffer.episode_starts[1:8].any()
    assert buffer.episode_starts[:20, 0].sum() == 3  # steps 0, 8 and 16 start episodes
    assert buffer.sample(64).hidden.dtype == th.float32


def test_save_load_round_trip_keeps_predictions(tmp_path):
    env = bit_env(n_envs=2)
    model = quick_model(env)
    model.learn(400)
    path = tmp_path / "model.zip"
    model.save(path)
    obs = env.reset()
    expected, expected_state = model.predict(obs, deterministic=True)

    for loaded in (SoftHGRN.load(path, env=env), SoftHGRN.load(path)):
        actions, state = loaded.predict(obs, deterministic=True)
        np.testing.assert_array_equal(actions, expected)
        np.testing.assert_allclose(state[0], expected_state[0], atol=1e-6)
        assert loaded.policy.temperature.alpha.item() == pytest.approx(model.policy.temperature.alpha.item())

    # another number of copies and agents: training continues
    other = bit_env(n_envs=3, n_agents=6)
    loaded = SoftHGRN.load(path, env=other)
    assert loaded.n_envs == 18 and loaded.policy.n_agents == 6
    loaded.learn(18 * 10, reset_num_timesteps=False)
    assert loaded.num_timesteps == model.num_timesteps + 180


def test_the_soft_policy_collects_with_epsilon_0_3_unless_told_otherwise():
    env = bit_env(n_envs=2)
    default = quick_model(env)
    assert (default.exploration_initial_eps, default.exploration_final_eps) == (0.3, 0.3)
    chosen = quick_model(env, exploration_initial_eps=1.0, exploration_final_eps=0.0)
    assert (chosen.exploration_initial_eps, chosen.exploration_final_eps) == (1.0, 0.0)
    sac = SACHGRN("GraphPolicy", env, policy_kwargs=dict(hidden_dim=16, n_heads=2))
    assert (sac.exploration_initial_eps, sac.exploration_final_eps) == (0.3, 0.3)


def test_stochastic_false_is_greedy_with_epsilon_greedy_exploration():
    env = bit_env(n_envs=2)
    model = quick_model(env, stochastic=False)
    assert model.exploration_initial_eps == 1.0 and model.exploration_final_eps == 0.05
    obs = env.reset()
    first, _ = model.predict(obs, deterministic=False)
    for _ in range(5):
        np.testing.assert_array_equal(model.predict(obs, deterministic=False)[0], first)
    q = th.tensor([[1.0, 3.0, 2.0]])
    assert model._next_value(q, th.tensor(0.5)).item() == pytest.approx(3.0)


def test_soft_value_matches_hand_computation():
    q = th.tensor([[1.0, 2.0], [0.0, 0.0]])
    alpha = th.tensor(0.5)
    expected = [0.5 * math.log(math.exp(2.0) + math.exp(4.0)), 0.5 * math.log(2.0)]
    np.testing.assert_allclose(soft_value(q, alpha).numpy(), expected, rtol=1e-6)


def test_logs_team_returns_and_temperature(tmp_path):
    env = bit_env(n_envs=2)
    model = quick_model(env, tensorboard_log=str(tmp_path), verbose=0)
    model.learn(8 * 40, log_interval=1, progress_bar=True)
    logged = model.logger.name_to_value
    for key in ("train/alpha", "train/entropy", "train/target_entropy", "train/q_loss"):
        assert key in logged
    assert logged["train/target_entropy"] == pytest.approx(0.2 * math.log(2))
    run_dirs = os.listdir(tmp_path)
    assert run_dirs == ["SoftHGRN_1"]
    assert any(name.startswith("events.out") for name in os.listdir(tmp_path / run_dirs[0]))


def test_team_return_logged_each_log_interval():
    env = bit_env(n_envs=2)
    model = quick_model(env)
    dumps = []
    model.dump_logs = lambda: dumps.append(dict(model._team_episodes[-1]))
    model.learn(8 * 16, log_interval=2)
    # 16 vec-steps of 2 copies with 8-step episodes = 4 team episodes -> 2 dumps
    assert len(dumps) == 2 and model._episode_num == 4
    assert all(0 <= episode["r"] <= 32 and episode["l"] == 8 for episode in dumps)


def test_sb3_callbacks_and_graph_eval_callback(tmp_path):
    env = bit_env(n_envs=2)
    model = quick_model(env)
    graph_eval = GraphEvalCallback(
        bit_env(n_envs=1, seed=5),
        n_eval_episodes=2,
        eval_freq=20,
        best_model_save_path=str(tmp_path / "best"),
        log_path=str(tmp_path),
        verbose=0,
    )
    sb3_eval = EvalCallback(bit_env(n_envs=1, seed=6), n_eval_episodes=4, eval_freq=20, verbose=0)
    checkpoint = CheckpointCallback(save_freq=20, save_path=str(tmp_path / "ckpt"))
    model.learn(8 * 40, callback=[graph_eval, sb3_eval, checkpoint])
    assert len(graph_eval.evaluations_results) == 2 and (tmp_path / "best" / "best_model.zip").exists()
    assert all(0 <= r <= 32 for results in graph_eval.evaluations_results for r in results)
    assert (tmp_path / "evaluations.npz").exists()
    assert np.isfinite(sb3_eval.last_mean_reward)
    assert sorted(os.listdir(tmp_path / "ckpt")) == ["rl_model_160_steps.zip", "rl_model_320_steps.zip"]


def test_rejects_bad_envs():
    with pytest.raises(TypeError, match="single-agent"):
        SoftHGRN("GraphPolicy", gym.make("CartPole-v1"))
    with pytest.raises(TypeError, match="not a graph VecEnv"):
        SoftHGRN("GraphPolicy", DummyVecEnv([lambda: gym.make("CartPole-v1")]))

    class ContinuousActions(NeighborBitEnv):
        def __init__(self):
            super().__init__()
            self.shared_action_space = gym.spaces.Box(-1, 1, shape=(2,))

    with pytest.raises(TypeError, match="Discrete action space"):
        SoftHGRN("GraphPolicy", make_graph_vec_env(ContinuousActions))


def test_rejects_partial_graph_batches():
    model = quick_model(bit_env(n_envs=2))
    obs = bit_env(n_envs=2).reset()
    with pytest.raises(ValueError, match="not a whole number of graphs of 4 agents"):
        model.predict({key: value[:6] for key, value in obs.items()})
    with pytest.raises(ValueError, match="single agent"):
        model.predict({key: value[0] for key, value in obs.items()})


def test_rejects_nan_rewards():
    env = make_graph_vec_env(lambda: DictOnlyEnv(reward=float("nan")), n_envs=1)
    model = quick_model(env)
    with pytest.raises(ValueError, match="non-finite rewards"):
        model.learn(30)


def test_load_onto_env_with_other_spaces_fails(tmp_path):
    model = quick_model(bit_env(n_envs=1))
    model.save(tmp_path / "m.zip")
    with pytest.raises(ValueError, match="spaces do not match"):
        SoftHGRN.load(tmp_path / "m.zip", env=make_graph_vec_env(DictOnlyEnv))


def test_same_seed_gives_the_same_training_run():
    parameters = []
    for _ in range(2):
        model = quick_model(bit_env(n_envs=2, seed=3), seed=11)
        model.learn(8 * 30)
        parameters.append(th.cat([p.detach().flatten() for p in model.policy.parameters()]))
    assert th.equal(parameters[0], parameters[1])
    other = quick_model(bit_env(n_envs=2, seed=3), seed=12)
    other.learn(8 * 30)
    assert not th.equal(parameters[0], th.cat([p.detach().flatten() for p in other.policy.parameters()]))


def test_gradient_steps_minus_one_takes_one_step_per_graph_collected():
    """SB3's ``gradient_steps=-1`` (as many gradient steps as collected): a collected step of 2 copies
    holds 2 graphs, and ``batch_size`` counts graphs, so 2 gradient steps, not one per agent (8)."""
    model = quick_model(bit_env(n_envs=2), gradient_steps=-1)
    model.learn(8 * 20)  # vec-steps 9..20 train (num_timesteps > learning_starts=64)
    assert model._n_updates == 12 * 2


def test_average_tau_deploys_a_polyak_average_and_collects_with_the_online_network(tmp_path):
    env = bit_env(n_envs=2)
    model = quick_model(env, policy_kwargs={**SMALL, "average_tau": 0.1})
    initial = [p.clone() for p in model.policy.q_net_average.parameters()]
    model.learn(400)
    assert not all(
        th.equal(a, b) for a, b in zip(model.policy.q_net_average.parameters(), initial, strict=True)
    )
    check_deployed_average(model, env, tmp_path)
    with pytest.raises(ValueError, match="average_tau"):
        quick_model(env, policy_kwargs={**SMALL, "average_tau": 0.0})


@pytest.mark.parametrize("algorithm", [SoftHGRN, SACHGRN])
def test_load_keeps_the_seeds_of_the_env_it_is_given(tmp_path, algorithm):
    """Evaluation envs seeded differently give different numbers after ``load``, each the numbers of
    the same env evaluated without the load (the model's own seed does not replace the env's)."""
    model = algorithm("GraphPolicy", bit_env(n_envs=2), learning_starts=64, batch_size=8,
                      policy_kwargs=SMALL, seed=0)  # fmt: skip
    model.save(tmp_path / "model.zip")

    def returns(env_seed: int, load: bool) -> list[float]:
        env = bit_env(n_envs=2, seed=env_seed)
        evaluated = algorithm.load(tmp_path / "model.zip", env=env) if load else model
        result, _ = evaluate_graph_policy(evaluated, env, 8, deterministic=True, return_episode_rewards=True)
        return result

    assert returns(1, load=True) != returns(2, load=True)
    assert returns(1, load=True) == returns(1, load=False)
    assert returns(2, load=True) == returns(2, load=False)


@pytest.mark.parametrize("algorithm", [SoftHGRN, SACHGRN])
def test_adam_is_fused_by_default_and_models_saved_unfused_learn_on(tmp_path, monkeypatch, algorithm):
    def optimizers(model):
        policy = model.policy
        if algorithm is SoftHGRN:
            return [policy.optimizer]
        return [policy.actor_optimizer, policy.critic_optimizer]

    options = dict(learning_starts=32, batch_size=4, train_freq=1, policy_kwargs=SMALL)
    model = algorithm("GraphPolicy", bit_env(n_envs=2), seed=0, **options)
    assert model.policy.optimizer_kwargs == {"fused": True}
    assert all(optimizer.defaults["fused"] for optimizer in optimizers(model))
    given = algorithm("GraphPolicy", bit_env(n_envs=2), **{**options, "policy_kwargs": {
        **SMALL, "optimizer_kwargs": {"foreach": False}}})  # fmt: skip
    assert given.policy.optimizer_kwargs == {"foreach": False}
    with monkeypatch.context() as patch:  # a model saved before Adam was fused by default
        patch.setattr(graph_policies, "fused_by_default", lambda _, kwargs: dict(kwargs or {}))
        earlier = algorithm("GraphPolicy", bit_env(n_envs=2), seed=1, **options).learn(80)
        assert not any(optimizer.defaults["fused"] for optimizer in optimizers(earlier))
        earlier.save(tmp_path / "earlier.zip")
    loaded = algorithm.load(tmp_path / "earlier.zip", env=bit_env(n_envs=2))
    before = [p.detach().clone() for p in loaded.policy.parameters()]
    loaded.learn(80, reset_num_timesteps=False)
    after = list(loaded.policy.parameters())
    assert all(th.isfinite(p).all() for p in after)
    assert any(not th.equal(b, a) for b, a in zip(before, after, strict=True))


def test_random_graph_policy_examples_run_as_documented():
    """The example of docs/usage.md (an env of three agent groups, actions within each agent's group)
    and the one of the class docstring run, and give what they say."""
    usage = run_snippet(python_block("usage.md", "RandomGraphPolicy(env, seed=0)"))
    assert usage["actions"].shape == (usage["env"].num_envs,) and usage["actions"].dtype == np.int64
    assert usage["state"] is None and np.isfinite(usage["mean_return"])
    docstring = run_snippet("from sb3_hgrn import *\n" + docstring_example(RandomGraphPolicy.__doc__))
    assert docstring["actions"].shape == (docstring["env"].num_envs,) and np.isfinite(docstring["std_return"])


def test_an_argument_soft_hgrn_adds_is_type_checked():
    """SoftHGRN checks the arguments it adds to the shared ones as SACHGRN does (tests/test_sac_hgrn.py)."""
    with pytest.raises(TypeError, match="_init_setup_model must be true or false, got 'no'"):
        quick_model(bit_env(n_envs=1), _init_setup_model="no")
