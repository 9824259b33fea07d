import gymnasium as gym
import numpy as np
import pytest

from sb3_hgrn import GraphVecEnv, make_graph_vec_env
from tests.toy_envs import DictOnlyEnv, NeighborBitEnv


def test_slots_are_copy_major_with_graph_observations():
    env = make_graph_vec_env(lambda: NeighborBitEnv(n_agents=4), n_envs=3, seed=0)
    assert env.num_envs == 12 and env.n_agents == 4 and env.n_copies == 3
    obs = env.reset()
    assert obs["obs"].shape == (12, 1) and obs["obs"].dtype == np.int8
    assert obs["neighbors"].shape == (12, 2) and obs["neighbors"].dtype == np.int32
    # neighbours index agents within the copy: slot 5 is agent 1 of copy 1, left neighbour agent 0
    np.testing.assert_array_equal(obs["neighbors"][5], [1, 0])


def test_rewards_dones_and_terminal_infos():
    env = make_graph_vec_env(lambda: NeighborBitEnv(n_agents=4, max_cycles=3), n_envs=2, seed=1)
    obs = env.reset()
    for _ in range(3):
        bits = obs["obs"][:, 0].reshape(2, 4)
        left_bits = np.roll(bits, 1, axis=1).reshape(-1)
        obs, rewards, dones, infos = env.step(left_bits)
        np.testing.assert_array_equal(rewards, np.ones(8, dtype=np.float32))
        assert dones.dtype == bool
    assert dones.all()
    for slot, info in enumerate(infos):
        assert info["TimeLimit.truncated"] is True
        assert info["terminal_observation"]["obs"].shape == (1,)
        assert info["team_episode"]["r"] == 12.0 and info["team_episode"]["l"] == 3
        np.testing.assert_array_equal(info["terminal_observation"]["neighbors"], [slot % 4, (slot - 1) % 4])


def test_seed_makes_resets_reproducible_and_copies_differ():
    first = make_graph_vec_env(lambda: NeighborBitEnv(n_agents=16), n_envs=2, seed=7).reset()["obs"]
    second = make_graph_vec_env(lambda: NeighborBitEnv(n_agents=16), n_envs=2, seed=7).reset()["obs"]
    np.testing.assert_array_equal(first, second)
    assert not np.array_equal(first[:16], first[16:])


def test_dict_only_parallel_env_is_adapted():
    env = make_graph_vec_env(lambda: DictOnlyEnv(n_agents=3, max_cycles=2), n_envs=2)
    obs = env.reset()
    assert obs["obs"].shape == (6, 2) and obs["neighbors"].shape == (6, 3)
    _, rewards, dones, _ = env.step(np.array([0, 1, 2, 2, 1, 0]))
    np.testing.assert_array_equal(rewards, [0, 1, 2, 2, 1, 0])
    assert not dones.any()
    _, _, dones, infos = env.step(np.zeros(6, dtype=int))
    assert dones.all() and infos[0]["team_episode"]["r"] == 3.0 and infos[3]["team_episode"]["r"] == 3.0


def test_get_attr_maps_slots_to_copies():
    env = make_graph_vec_env(lambda: NeighborBitEnv(n_agents=4, max_cycles=5), n_envs=2)
    assert env.get_attr("max_cycles", indices=[0, 7]) == [5, 5]
    env.set_attr("max_cycles", 9, indices=[4])
    assert [copy.max_cycles for copy in env.envs] == [5, 9]


def test_single_agent_gym_env_is_rejected():
    with pytest.raises(TypeError, match="single-agent"):
        make_graph_vec_env(lambda: gym.make("CartPole-v1"))


def test_env_without_graph_is_rejected():
    class NoGraph(DictOnlyEnv):
        neighbors = None

    with pytest.raises(TypeError, match="neighbors"):
        make_graph_vec_env(NoGraph)


def test_unknown_env_name_and_bad_arguments():
    with pytest.raises(ValueError, match="Unknown env"):
        make_graph_vec_env("nope_v0")
    with pytest.raises(ValueError, match="n_envs"):
        make_graph_vec_env(NeighborBitEnv, n_envs=0)
    with pytest.raises(ValueError, match="same number of agents"):
        GraphVecEnv([lambda: NeighborBitEnv(4), lambda: NeighborBitEnv(5)])
    env = make_graph_vec_env(NeighborBitEnv)
    env.reset()
    with pytest.raises(ValueError, match="actions"):
        env.step(np.zeros(3, dtype=int))


def test_registered_surviving_env_and_render():
    env = make_graph_vec_env(
        "surviving_v0", n_envs=2, seed=0, env_kwargs=dict(n_agents=10, map_size=12, render_mode="rgb_array")
    )
    obs = env.reset()
    assert env.num_envs == 20 and obs["obs"].dtype == np.int8
    assert (obs["neighbors"][:10, 0] == np.arange(10)).all()  # self first, indices within the copy
    assert (obs["neighbors"][10:, 0] == np.arange(10)).all()
    frame = env.render()
    assert frame.ndim == 3 and frame.shape[2] == 3 and frame.dtype == np.uint8
    assert env.render_mode == "rgb_array"


def test_neighbour_indices_out_of_range_are_rejected():
    class WrongGraph(NeighborBitEnv):
        def neighbors(self):
            graph = super().neighbors()
            graph[0, 1] = self.n_agents  # no such agent
            return graph

    with pytest.raises(ValueError, match=r"agent indices in \[-1, 3\]"):
        make_graph_vec_env(WrongGraph).reset()


@pytest.mark.parametrize(
    "env_name, env_kwargs",
    [
        ("surviving_v0", dict(n_agents=20, map_size=16, n_resources=3, max_cycles=30)),
        ("uav_mbs_v0", dict(n_uavs=10, n_users=60, max_cycles=30, observation_mode="compact")),
        ("pursuit_v0", dict(map_size=30, max_cycles=30)),
    ],
)
def test_registered_envs_list_distinct_neighbours(env_name, env_kwargs):
    """The attention counts a repeated neighbour once; these envs never list one twice, so that rule
    does not change what they learn."""
    env = make_graph_vec_env(env_name, n_envs=2, seed=0, env_kwargs=env_kwargs)
    obs = env.reset()
    rng = np.random.default_rng(0)
    for _ in range(40):
        for row in obs["neighbors"]:
            listed = row[row >= 0]
            assert len(np.unique(listed)) == len(listed), row
        obs, *_ = env.step(rng.integers(0, env.action_space.n, env.num_envs))
