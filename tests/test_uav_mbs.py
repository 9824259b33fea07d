import math

import numpy as np
import pytest
from pettingzoo.test import parallel_api_test

from sb3_hgrn.envs import uav_mbs_v0
from sb3_hgrn.envs.graph import grid_neighbors
from sb3_hgrn.envs.uav_mbs_v0 import UAVMBSEnv, connected_component_labels, view_offsets

E, SE, S, SW, W, NW, N, NE = range(8)
HALF = 8  # action + HALF: the same direction at half thrust
HOVER = 16
RASTER_DIM, COMPACT_DIM = 1613, 44
UAV_MAP, USER_MAP, OBSTACLE_MAP = slice(20, 547), slice(547, 1074), slice(1074, 1601)


def at_cell(x: int, y: int) -> tuple[float, float]:
    """A position whose raster cell is ``(x, y)``: the middle of that cell."""
    return (x - 13 + 0.5) / 200, (y - 13 + 0.5) / 200


# Hand-made configuration (cells). Components: {0, 1}, {2}, {3}, and the chain {4, 5, 6} (4 and 6 are
# 30 cells apart, linked through 5).
HAND_UAV_CELLS = [(50, 50), (60, 50), (150, 150), (100, 150), (20, 150), (35, 150), (50, 150)]
HAND_USER_CELLS = [
    (50, 50),  # u0: UAV 0 only (UAV 1 is exactly 10 cells away: not covered, the range is strict)
    (55, 50),  # u1: UAVs 0 and 1
    (65, 50),  # u2: UAV 1 only
    (68, 50),  # u3: UAV 1 only
    (150, 150),  # u4: UAV 2 only
    (200, 200),  # u5: nobody
    (20, 150),  # u6: UAV 4 only
    (43, 150),  # u7: UAVs 5 and 6
    (50, 153),  # u8: UAV 6 only
]
# (individual, or -1) + 0.1 * (total - individual) / (|G| - 1): component {0, 1} covers u0..u3, the chain
# covers u6..u8.
HAND_COVERAGE_REWARDS = [
    1 + 0.1 * 3 / 1,
    2 + 0.1 * 2 / 1,
    1.0,
    -1.0,
    1 + 0.1 * 2 / 2,
    -1 + 0.1 * 3 / 2,
    1 + 0.1 * 2 / 2,
]


def hand_env(**kwargs) -> UAVMBSEnv:
    defaults = dict(
        n_uavs=len(HAND_UAV_CELLS),
        n_users=len(HAND_USER_CELLS),
        n_clusters=1,
        uav_positions=[at_cell(*cell) for cell in HAND_UAV_CELLS],
        user_positions=[at_cell(*cell) for cell in HAND_USER_CELLS],
    )
    return uav_mbs_v0.parallel_env(**{**defaults, **kwargs})


def single_uav_env(position: tuple[float, float], **kwargs) -> UAVMBSEnv:
    """One UAV and one user far away in a corner (so the coverage part of the reward is -1)."""
    return uav_mbs_v0.parallel_env(
        n_uavs=1, n_users=1, n_clusters=1, uav_positions=[position], user_positions=[(0.0, 0.0)], **kwargs
    )


def decode_bits(bits: np.ndarray) -> int:
    return int(bits @ (2 ** np.arange(len(bits) - 1, -1, -1)))


def offset_index(dx: int, dy: int) -> int:
    return int(np.flatnonzero((view_offsets() == (dx, dy)).all(axis=1))[0])


def test_parallel_api():
    parallel_api_test(uav_mbs_v0.parallel_env(n_uavs=6, n_users=30, max_cycles=20), num_cycles=30)
    parallel_api_test(uav_mbs_v0.parallel_env(observation_mode="compact", max_cycles=20), num_cycles=30)


def test_view_offsets_are_the_527_of_the_half_open_disc():
    offsets = view_offsets()
    assert offsets.shape == (527, 2)
    assert len({tuple(offset) for offset in offsets.tolist()}) == 527
    assert np.all((offsets**2).sum(axis=1) <= 13**2) and offsets.min() == -13 and offsets.max() == 12
    closed_disc = [(dx, dy) for dx in range(-13, 14) for dy in range(-13, 14) if dx * dx + dy * dy <= 169]
    assert set(closed_disc) - {tuple(offset) for offset in offsets.tolist()} == {(13, 0), (0, 13)}


def test_spaces_and_observation_sizes():
    default = uav_mbs_v0.parallel_env()
    assert default.possible_agents[0] == "uav_0" and default.possible_agents[-1] == "uav_19"
    assert default.shared_observation_space.shape == (RASTER_DIM,)
    assert default.shared_observation_space.dtype == np.float32
    assert default.action_space("uav_3").n == 17
    assert default.max_neighbors == 16
    assert uav_mbs_v0.parallel_env(observation_mode="compact").shared_observation_space.shape == (
        COMPACT_DIM,
    )
    for mode, dim in (("raster", RASTER_DIM), ("compact", COMPACT_DIM)):
        spaces = []
        for n_uavs, n_users in ((20, 120), (30, 120), (3, 10)):
            env = uav_mbs_v0.parallel_env(n_uavs=n_uavs, n_users=n_users, observation_mode=mode)
            observations = env.reset_arrays(seed=0)
            assert observations.shape == (n_uavs, dim) and observations.dtype == np.float32
            for _ in range(3):
                observations, *_ = env.step_arrays(np.arange(n_uavs) % 17)
            assert all(env.shared_observation_space.contains(obs) for obs in observations)
            spaces.append(env.shared_observation_space)
        assert all(space == spaces[0] for space in spaces)  # a model trained with 20 UAVs loads onto 30


def run_episode(env: UAVMBSEnv, seed: int | None, n_steps: int = 30):
    observations = [env.reset_arrays(seed=seed)]
    rewards, graphs, infos = [], [], []
    action_rng = np.random.default_rng(123)
    for _ in range(n_steps):
        obs, reward, _, _, info = env.step_arrays(action_rng.integers(0, 17, size=env.n_agents))
        observations.append(obs)
        rewards.append(reward)
        graphs.append(env.neighbors())
        infos.append(list(info.values()))
    return np.array(observations), np.array(rewards), np.array(graphs), np.array(infos)


def test_same_seed_gives_identical_episodes_and_unseeded_resets_continue():
    env_a, env_b = uav_mbs_v0.parallel_env(), uav_mbs_v0.parallel_env()
    first_a, first_b = run_episode(env_a, seed=7), run_episode(env_b, seed=7)
    for array_a, array_b in zip(first_a, first_b, strict=True):
        np.testing.assert_array_equal(array_a, array_b)
    assert not np.array_equal(run_episode(env_a, seed=8)[0], first_a[0])
    second_a = run_episode(env_a, seed=None)
    assert not np.array_equal(second_a[0], first_a[0])
    run_episode(env_b, seed=8)
    np.testing.assert_array_equal(run_episode(env_b, seed=None)[0], second_a[0])


def test_random_placement():
    env = uav_mbs_v0.parallel_env()
    for seed in range(10):
        env.reset_arrays(seed=seed)
        uavs, users = env.uav_positions(), env.user_positions()
        assert uavs.min() >= 0.1 and uavs.max() <= 0.9
        assert users.shape == (120, 2) and users.min() >= 0.0 and users.max() <= 1.0
        np.testing.assert_array_equal(env.user_cells(), np.minimum((users * 200 + 13).astype(int), 212))
        centres = env._cluster_centres()
        assert centres.min() >= 0.15 and centres.max() <= 0.85
        assert min(math.dist(a, b) for i, a in enumerate(centres) for b in centres[i + 1 :]) >= 0.25
        cluster_means = np.array([users[cluster::3].mean(axis=0) for cluster in range(3)])
        assert (
            min(math.dist(a, b) for i, a in enumerate(cluster_means) for b in cluster_means[i + 1 :]) > 0.15
        )
    with pytest.raises(RuntimeError):
        uav_mbs_v0.parallel_env(n_clusters=30).reset_arrays(seed=0)


@pytest.mark.parametrize("action", range(16))
def test_thrust_from_rest_moves_by_the_full_thrust(action):
    env = single_uav_env((0.5, 0.5))
    env.reset_arrays(seed=0)
    _, _, _, _, info = env.step_arrays(np.array([action]))
    angle = -(action % 8) * math.pi / 4
    thrust = 0.02 if action < HALF else 0.01
    expected_velocity = thrust * np.array([math.cos(angle), math.sin(angle)])
    np.testing.assert_allclose(env.uav_velocities()[0], expected_velocity, atol=1e-15)
    np.testing.assert_allclose(env.uav_positions()[0], 0.5 + expected_velocity, atol=1e-15)
    assert info["energy"] == pytest.approx(0.5 + 0.5 * thrust / 0.02)


def test_axis_aligned_full_thrust_and_speed_cap():
    env = single_uav_env((0.5, 0.5))
    env.reset_arrays(seed=0)
    env.step_arrays(np.array([E]))  # |v| = 0.02 exactly: the original zeroed v here
    assert env.uav_velocities()[0].tolist() == [0.02, 0.0]
    np.testing.assert_allclose(env.uav_positions()[0], [0.52, 0.5])
    env.step_arrays(np.array([E]))  # v = 0.04 is capped to 0.02
    np.testing.assert_allclose(env.uav_velocities()[0], [0.02, 0.0])
    np.testing.assert_allclose(env.uav_positions()[0], [0.54, 0.5])
    env.step_arrays(np.array([HOVER]))  # no friction: the UAV glides on
    np.testing.assert_allclose(env.uav_positions()[0], [0.56, 0.5])
    env.step_arrays(np.array([W + HALF]))
    np.testing.assert_allclose(env.uav_velocities()[0], [0.01, 0.0])
    _, _, _, _, info = env.step_arrays(np.array([N]))  # |(0.01, 0.02)| > 0.02: rescaled to 0.02
    np.testing.assert_allclose(env.uav_velocities()[0], 0.02 * np.array([1, 2]) / math.sqrt(5))
    np.testing.assert_allclose(
        env.uav_positions()[0], [0.57 + 0.02 / math.sqrt(5), 0.5 + 0.04 / math.sqrt(5)]
    )
    assert info["energy"] == pytest.approx(1.0)

    env.reset_arrays(seed=0)
    env.step_arrays(np.array([NE]))
    env.step_arrays(np.array([E]))
    raw = 0.02 * np.array([1 / math.sqrt(2) + 1, 1 / math.sqrt(2)])
    np.testing.assert_allclose(env.uav_velocities()[0], raw * 0.02 / np.linalg.norm(raw))
    assert np.linalg.norm(env.uav_velocities()[0]) == pytest.approx(0.02)


def test_border_clips_position_and_costs_one():
    env = single_uav_env((0.995, 0.5))
    env.reset_arrays(seed=0)
    _, rewards, *_ = env.step_arrays(np.array([E]))  # unclipped x = 1.015: pressed
    assert env.uav_positions()[0].tolist() == [1.0, 0.5]
    assert env.uav_cells()[0].tolist() == [212, 113]
    np.testing.assert_allclose(rewards, [(-1 - 1) / 1.0])
    _, rewards, *_ = env.step_arrays(np.array([W + HALF]))  # v = (0.01, 0): still pressing, e = 0.75
    np.testing.assert_allclose(rewards, [(-1 - 1) / 0.75], rtol=1e-6)
    _, rewards, *_ = env.step_arrays(np.array([W + HALF]))  # v = 0: at the border but not pressing
    assert env.uav_positions()[0].tolist() == [1.0, 0.5]
    np.testing.assert_allclose(rewards, [-1 / 0.5])
    _, rewards, *_ = env.step_arrays(np.array([SW]))  # moving away
    np.testing.assert_allclose(rewards, [-1 / 1.0])


def test_reward_on_hand_made_configuration():
    env = hand_env()
    env.reset_arrays(seed=0)
    _, rewards, terminated, truncated, info = env.step_arrays(np.full(7, HOVER))
    assert rewards.dtype == np.float32
    np.testing.assert_allclose(rewards, np.array(HAND_COVERAGE_REWARDS) / 0.5, rtol=1e-6)
    assert not terminated.any() and not truncated.any()
    assert info["energy"] == 0.5
    assert info["coverage"] == pytest.approx(8 / 9)  # all users but u5
    assert info["fairness"] == pytest.approx(8**2 / (9 * 8))

    # Energy divides the reward: UAV 3 (no users) flies at full thrust, UAV 2 at half thrust.
    _, rewards, _, _, info = env.step_arrays(np.array([HOVER, HOVER, W + HALF, E, HOVER, HOVER, HOVER]))
    expected = np.array(HAND_COVERAGE_REWARDS) / np.array([0.5, 0.5, 0.75, 1.0, 0.5, 0.5, 0.5])
    np.testing.assert_allclose(rewards, expected, rtol=1e-6)
    assert info["energy"] == pytest.approx((5 * 0.5 + 0.75 + 1.0) / 7)


def test_components_use_the_full_graph_not_the_truncated_neighbor_lists():
    env = hand_env(max_neighbors=2)
    env.reset_arrays(seed=0)
    _, rewards, *_ = env.step_arrays(np.full(7, HOVER))
    np.testing.assert_allclose(rewards, np.array(HAND_COVERAGE_REWARDS) / 0.5, rtol=1e-6)
    neighbor_lists = env.neighbors()
    assert neighbor_lists.tolist() == [[0, 1], [1, 0], [2, -1], [3, -1], [4, 5], [5, 4], [6, 5]]
    assert not neighbor_lists.flags.writeable


def test_neighbors_are_self_first_and_match_grid_neighbors():
    env = uav_mbs_v0.parallel_env(n_uavs=40)
    env.reset_arrays(seed=3)
    rng = np.random.default_rng(0)
    for _ in range(5):
        env.step_arrays(rng.integers(0, 17, size=40))
        neighbor_lists = env.neighbors()
        np.testing.assert_array_equal(neighbor_lists[:, 0], np.arange(40))
        np.testing.assert_array_equal(neighbor_lists, grid_neighbors(env.uav_cells(), 18, 16, "euclidean"))
    env = hand_env()
    env.reset_arrays(seed=0)
    assert env.neighbors()[5, :4].tolist() == [5, 4, 6, -1]  # equal distances: lower index first


def test_connected_components_of_two_far_apart_clusters():
    left = [at_cell(20 + 15 * i, 100) for i in range(5)]  # a chain, 15 cells apart
    right = [at_cell(200, 20 + 10 * i) for i in range(5)]
    env = uav_mbs_v0.parallel_env(
        n_uavs=10, n_users=2, n_clusters=1, uav_positions=left + right, user_positions=[(0.5, 0.5)] * 2
    )
    env.reset_arrays(seed=0)
    adjacency = (env.uav_cells()[:, None, :] - env.uav_cells()[None, :, :]) ** 2
    labels = connected_component_labels(adjacency.sum(axis=2) <= 18**2)
    assert labels.tolist() == [0] * 5 + [5] * 5
    _, rewards, *_ = env.step_arrays(np.full(10, HOVER))
    np.testing.assert_allclose(rewards, -1 / 0.5)  # nobody covers anyone: no shared part


def test_connected_component_labels_match_scipy():
    from scipy.sparse import csgraph

    rng = np.random.default_rng(0)
    for n_nodes, density in ((1, 0.0), (12, 0.1), (40, 0.05), (60, 0.02), (30, 0.5)):
        upper = np.triu(rng.random((n_nodes, n_nodes)) < density, 1)
        adjacency = upper | upper.T | np.eye(n_nodes, dtype=bool)
        labels = connected_component_labels(adjacency)
        n_components, expected = csgraph.connected_components(adjacency, directed=False)
        assert len(np.unique(labels)) == n_components
        np.testing.assert_array_equal(
            labels[:, None] == labels[None, :], expected[:, None] == expected[None, :]
        )
        assert np.all(labels <= np.arange(n_nodes)) and np.all(labels[labels] == labels)


def test_coverage_and_fairness_info():
    # One UAV, two users: u0 under the UAV, u1 40 cells east. The UAV hovers 2 steps, then flies east.
    env = uav_mbs_v0.parallel_env(
        n_uavs=1,
        n_users=2,
        n_clusters=1,
        uav_positions=[at_cell(100, 100)],
        user_positions=[at_cell(100, 100), at_cell(140, 100)],
    )
    env.reset_arrays(seed=0)
    for _ in range(2):
        _, _, _, _, info = env.step_arrays(np.array([HOVER]))
        assert info["coverage"] == pytest.approx(0.5)  # counts (k, 0) after k steps
        assert info["fairness"] == pytest.approx(0.5)  # k^2 / (2 * k^2)
    positions = []
    for _ in range(4):
        _, _, _, _, info = env.step_arrays(np.array([E]))
        positions.append(env.uav_cells()[0, 0])
    assert positions == [104, 108, 112, 116]  # u0 covered until x = 108, u1 from x = 131
    assert info["coverage"] == pytest.approx((4 + 0) / 2 / 6)  # u0 covered on 4 of 6 steps
    assert info["fairness"] == pytest.approx(1.0 / 2)

    far = single_uav_env((0.9, 0.9))
    far.reset_arrays(seed=0)
    _, _, _, _, info = far.step_arrays(np.array([HOVER]))
    assert info == {"coverage": 0.0, "fairness": 0.0, "energy": 0.5}


def test_raster_observation_layout():
    env = hand_env()
    observations = env.reset_arrays(seed=0)
    assert observations.shape == (7, RASTER_DIM)
    first = observations[0]
    assert decode_bits(first[0:10]) == 50 and decode_bits(first[10:20]) == 50
    uav_map, user_map = first[UAV_MAP], first[USER_MAP]
    assert uav_map[offset_index(0, 0)] == 1 and uav_map[offset_index(10, 0)] == 1 and uav_map.sum() == 2
    assert user_map[offset_index(0, 0)] == 1 and user_map[offset_index(5, 0)] == 1
    assert user_map.sum() == 2  # u2 and u3 (15 and 18 cells away) lie outside the disc
    assert first[OBSTACLE_MAP].sum() == 0
    np.testing.assert_array_equal(first[1601:1603], [0, 0])
    assert decode_bits(first[1603:1613]) == 0
    fifth = observations[4]  # UAV 4 at (20, 150): cells x < 13 are obstacles
    obstacles = fifth[OBSTACLE_MAP]
    assert obstacles[offset_index(-8, 0)] == 1 and obstacles[offset_index(-7, 0)] == 0
    assert obstacles.sum() == np.sum(view_offsets()[:, 0] < -7)
    assert decode_bits(fifth[1603:1613]) == 4

    observations, *_ = env.step_arrays(np.array([E, HOVER, HOVER, HOVER, HOVER, HOVER, N + HALF]))
    np.testing.assert_allclose(observations[0, 1601:1603], [1, 0])
    np.testing.assert_allclose(observations[6, 1601:1603], [0, 0.5], atol=1e-7)
    assert decode_bits(observations[0, 0:10]) == 54  # 50 + 0.02 * 200
    assert observations[0, UAV_MAP][offset_index(6, 0)] == 1  # UAV 1 is now 6 cells east


def test_raster_counts_uavs_sharing_a_cell():
    env = uav_mbs_v0.parallel_env(
        n_uavs=3,
        n_users=1,
        n_clusters=1,
        uav_positions=[at_cell(80, 80)] * 2 + [at_cell(82, 80)],
        user_positions=[at_cell(80, 81)],
    )
    observations = env.reset_arrays(seed=0)
    np.testing.assert_array_equal(observations[:, UAV_MAP][:, offset_index(0, 0)], [2, 2, 1])
    np.testing.assert_array_equal(observations[:, USER_MAP][:, offset_index(-2, 1)], [0, 0, 1])
    np.testing.assert_array_equal(observations[:, USER_MAP][:, offset_index(0, 1)], [1, 1, 0])
    observations, *_ = env.step_arrays(np.array([E, HOVER, HOVER]))  # UAV 0 moves 4 cells east
    np.testing.assert_array_equal(observations[:, UAV_MAP][:, offset_index(0, 0)], [1, 1, 1])


def test_compact_observation_layout():
    env = hand_env(observation_mode="compact")
    observations = env.reset_arrays(seed=0)
    assert observations.shape == (7, COMPACT_DIM)
    middle = observations[5]  # UAV 5 at (35, 150): neighbours 4 and 6 at 15 cells, user u7 8 cells east
    np.testing.assert_allclose(middle[0:2], at_cell(35, 150), rtol=1e-6)
    np.testing.assert_array_equal(middle[2:4], [0, 0])
    np.testing.assert_allclose(middle[4:12], [-15 / 18, 0, 0, 0, 15 / 18, 0, 0, 0], rtol=1e-6)
    np.testing.assert_array_equal(middle[12:24], 0)
    np.testing.assert_allclose(middle[24:26], [0.8, 0], rtol=1e-6)
    np.testing.assert_array_equal(middle[26:44], 0)
    second = observations[1]  # UAV 1 at (60, 50): UAV 0 and users u2 (5), u1 (5), u3 (8) in range
    np.testing.assert_allclose(second[4:8], [-10 / 18, 0, 0, 0], rtol=1e-6)
    np.testing.assert_allclose(second[24:30], [-0.5, 0, 0.5, 0, 0.8, 0], rtol=1e-6)

    observations, *_ = env.step_arrays(np.array([E, HOVER, HOVER, HOVER, HOVER, HOVER, HOVER]))
    np.testing.assert_allclose(observations[1, 4:8], [-6 / 18, 0, 1, 0], rtol=1e-6)  # UAV 0 flies east
    np.testing.assert_allclose(observations[0, 2:4], [1, 0])
    assert all(env.shared_observation_space.contains(obs) for obs in observations)


def test_truncation_at_max_cycles():
    env = uav_mbs_v0.parallel_env(n_uavs=4, n_users=12, max_cycles=5)
    env.reset(seed=0)
    for step in range(1, 6):
        _, _, terminations, truncations, infos = env.step({agent: HOVER for agent in env.agents})
        assert not any(terminations.values())
        assert all(truncations.values()) == (step == 5)
        assert set(infos["uav_0"]) == {"coverage", "fairness", "energy"}
    assert env.agents == []
    with pytest.raises(RuntimeError):
        env.step_arrays(np.zeros(4, dtype=np.int64))


@pytest.mark.parametrize(
    "kwargs",
    [
        dict(n_uavs=0),
        dict(n_uavs=1025),
        dict(n_users=0),
        dict(n_clusters=0),
        dict(n_users=2, n_clusters=3),
        dict(max_cycles=0),
        dict(comm_range=0),
        dict(coverage_range=-1),
        dict(max_neighbors=0),
        dict(observation_mode="image"),
        dict(render_mode="ansi"),
        dict(n_uavs=2, uav_positions=[[0.5, 0.5]]),
        dict(n_uavs=2, uav_positions=[[0.5, 0.5], [0.5, 1.1]]),
        dict(n_uavs=2, uav_positions=[[0.5, 0.5], [float("nan"), 0.5]]),
        dict(n_users=2, user_positions=[[0.5, 0.5, 0.5], [0.1, 0.2, 0.3]]),
        dict(n_users=1, user_positions=[[-0.1, 0.5]]),
    ],
)
def test_invalid_arguments_raise(kwargs):
    with pytest.raises(ValueError):
        uav_mbs_v0.parallel_env(**kwargs)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(n_users="30"), "n_users must be an integer >= 1, got '30'"),
        (
            dict(n_clusters=2.0),
            r"n_clusters must be an integer in 1..120 \(at most one cluster per user\), got 2.0",
        ),
        (dict(max_cycles="5"), "max_cycles must be an integer >= 1, got '5'"),
        (dict(comm_range="18"), "comm_range must be a number > 0, got '18'"),
        (dict(coverage_range=0), "coverage_range must be a number > 0, got 0"),
        (dict(max_neighbors="16"), "max_neighbors must be an integer >= 1, got '16'"),
    ],
)
def test_a_wrongly_typed_argument_names_it_and_its_range(kwargs, message):
    with pytest.raises(ValueError, match=message):
        uav_mbs_v0.parallel_env(**kwargs)


@pytest.mark.parametrize("n_uavs", [0, 1025, 2.0])
def test_the_uav_count_is_an_integer_in_its_range(n_uavs):
    with pytest.raises(ValueError, match=f"n_uavs must be an integer in 1..1024 .*, got {n_uavs!r}"):
        uav_mbs_v0.parallel_env(n_uavs=n_uavs)


def test_invalid_actions_raise():
    env = hand_env()
    env.reset_arrays(seed=0)
    for actions in ([0] * 6, [0] * 6 + [17], [0] * 6 + [-1]):
        with pytest.raises(ValueError):
            env.step_arrays(np.array(actions))


def test_render_rgb_array():
    env = hand_env(render_mode="rgb_array")
    env.reset_arrays(seed=0)
    image = env.render()
    assert image.shape == (452, 452, 3) and image.dtype == np.uint8
    np.testing.assert_array_equal(image[0, 0], [150, 150, 150])  # obstacle margin

    def pixel(x: int, y: int) -> np.ndarray:
        return image[451 - (2 * y + 1), 2 * x + 1]

    np.testing.assert_array_equal(pixel(50, 50), [220, 30, 30])  # UAV 0
    np.testing.assert_array_equal(pixel(200, 200), [40, 90, 230])  # u5, not covered
    np.testing.assert_array_equal(pixel(68, 50), [30, 160, 60])  # u3, covered
    np.testing.assert_array_equal(pixel(100, 100), [255, 255, 255])


def test_render_without_mode_warns_and_returns_none():
    env = hand_env()
    env.reset_arrays(seed=0)
    with pytest.warns(UserWarning):
        assert env.render() is None


def test_render_human_with_dummy_display(monkeypatch):
    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")
    env = hand_env(render_mode="human")
    env.reset_arrays(seed=0)
    assert env.render() is None
    env.close()
