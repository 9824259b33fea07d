"""A model trained with N agents loads and runs on the same env with M != N agents, on every env."""

import numpy as np
import pytest

from sb3_hgrn import SoftHGRN, evaluate_graph_policy, make_graph_vec_env

# env name -> (kwargs with N agents, kwargs with M agents, N, M)
TRANSFERS = {
    "surviving_v0": (
        dict(n_agents=20, map_size=12, n_resources=2, max_cycles=20),
        dict(n_agents=40, map_size=12, n_resources=2, max_cycles=20),
        20,
        40,
    ),
    "uav_mbs_v0": (
        dict(n_uavs=4, n_users=12, max_cycles=10),
        dict(n_uavs=7, n_users=12, max_cycles=10),
        4,
        7,
    ),
    "pursuit_v0": (dict(map_size=16, max_cycles=10), dict(map_size=20, max_cycles=10), 3, 5),
    "ctc_v0": (
        dict(n_hunters=3, n_red_banks=2, n_blue_banks=2, map_size=12, max_cycles=10),
        dict(n_hunters=6, n_red_banks=1, n_blue_banks=3, map_size=12, max_cycles=10),
        7,
        10,
    ),
}


@pytest.mark.parametrize("name", list(TRANSFERS))
def test_model_trained_with_n_agents_runs_with_m_agents(tmp_path, name):
    trained_kwargs, other_kwargs, n_agents, m_agents = TRANSFERS[name]
    env = make_graph_vec_env(name, n_envs=2, seed=0, env_kwargs=trained_kwargs)
    assert env.n_agents == n_agents
    model = SoftHGRN("GraphPolicy", env, learning_starts=40, train_freq=1, batch_size=4,
                     policy_kwargs=dict(hidden_dim=16), seed=0)  # fmt: skip
    model.learn(3 * 10 * env.num_envs)
    model.save(tmp_path / "model.zip")

    other = make_graph_vec_env(name, seed=1, env_kwargs=other_kwargs)
    assert other.n_agents == m_agents
    loaded = SoftHGRN.load(tmp_path / "model.zip", env=other)
    assert loaded.policy.n_agents == m_agents
    mean, _ = evaluate_graph_policy(loaded, other, n_eval_episodes=1)
    assert np.isfinite(mean)
    actions, _ = loaded.predict(other.reset(), deterministic=True)
    assert actions.shape == (m_agents,)
    loaded.learn(2 * other.num_envs, reset_num_timesteps=False)  # and training goes on


def test_set_env_moves_a_model_to_another_agent_count():
    kwargs = dict(map_size=12, n_resources=2, max_cycles=20)
    env = make_graph_vec_env("surviving_v0", n_envs=2, seed=0, env_kwargs=dict(n_agents=20, **kwargs))
    model = SoftHGRN("GraphPolicy", env, learning_starts=40, policy_kwargs=dict(hidden_dim=16), seed=0)
    model.learn(2 * env.num_envs)
    other = make_graph_vec_env("surviving_v0", seed=1, env_kwargs=dict(n_agents=40, **kwargs))
    model.set_env(other, force_reset=False)
    assert model.n_envs == 40 and model.policy.n_agents == 40 and model.replay_buffer.n_agents == 40
    before = model.num_timesteps
    model.learn(3 * other.num_envs, reset_num_timesteps=False)
    assert model.num_timesteps >= before + 3 * 40
