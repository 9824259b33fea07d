import numpy as np
import pytest
from pettingzoo.test import parallel_api_test

from sb3_hgrn import make_graph_vec_env
from sb3_hgrn.envs import surviving_v0
from sb3_hgrn.envs.graph import grid_neighbors
from sb3_hgrn.envs.surviving_v0 import SurvivingEnv

UP, DOWN, LEFT, RIGHT, EAT = range(5)  # x - 1, x + 1, y - 1, y + 1, eat


def small_env(**kwargs) -> SurvivingEnv:
    """An 8 x 8 map (6 x 6 interior) without resource points unless given, so no food regrows."""
    defaults = dict(n_agents=3, map_size=8, n_resources=0, comm_range=2, max_neighbors=4)
    return surviving_v0.parallel_env(**{**defaults, **kwargs})


def food_map_with(cells_and_food: dict[tuple[int, int], int], map_size: int = 8) -> np.ndarray:
    """Interior food map ``(map_size - 2, map_size - 2)`` with food on the given ``(x, y)`` cells."""
    food = np.zeros((map_size - 2, map_size - 2), dtype=np.int64)
    for (x, y), amount in cells_and_food.items():
        food[x - 1, y - 1] = amount
    return food


def decode_position(observation: np.ndarray, bits: int = 3) -> tuple[int, int]:
    powers = 2 ** np.arange(bits - 1, -1, -1)
    return int(observation[:bits] @ powers), int(observation[bits : 2 * bits] @ powers)


def test_parallel_api():
    parallel_api_test(surviving_v0.parallel_env(n_agents=12, map_size=16, max_cycles=30), num_cycles=40)


def test_spaces_and_observation_size_do_not_depend_on_n_agents():
    default = surviving_v0.parallel_env()
    assert default.shared_observation_space.shape == (39,)
    assert default.shared_observation_space.dtype == np.int8
    assert default.action_space("agent_0").n == 5
    assert default.max_neighbors == 16
    assert default.possible_agents[-1] == "agent_99"
    for n_agents in (1, 20, 1000):
        env = surviving_v0.parallel_env(n_agents=n_agents)
        observations = env.reset_arrays(seed=0)
        assert observations.shape == (n_agents, 39) and observations.dtype == np.int8
    assert surviving_v0.parallel_env(map_size=100, n_agents=50).shared_observation_space.shape == (
        2 * 7 + 29,
    )


def run_episode(env: SurvivingEnv, seed: int | None, n_steps: int = 60):
    observations = [env.reset_arrays(seed=seed)]
    rewards, neighbor_lists = [], []
    action_rng = np.random.default_rng(123)
    for _ in range(n_steps):
        obs, reward, _, _, _ = env.step_arrays(action_rng.integers(0, 5, size=env.n_agents))
        observations.append(obs)
        rewards.append(reward)
        neighbor_lists.append(env.neighbors())
    return np.array(observations), np.array(rewards), np.array(neighbor_lists)


def test_same_seed_gives_identical_episodes_and_unseeded_resets_continue():
    env_a, env_b = surviving_v0.parallel_env(n_agents=30), surviving_v0.parallel_env(n_agents=30)
    first_a, first_b = run_episode(env_a, seed=7), run_episode(env_b, seed=7)
    for array_a, array_b in zip(first_a, first_b, strict=True):
        np.testing.assert_array_equal(array_a, array_b)
    assert not np.array_equal(run_episode(env_a, seed=8)[0], first_a[0])
    second_a = run_episode(env_a, seed=None)
    assert not np.array_equal(second_a[0], first_a[0])
    run_episode(env_b, seed=8)
    np.testing.assert_array_equal(run_episode(env_b, seed=None)[0], second_a[0])


def test_observation_layout_on_hand_made_map():
    env = small_env(
        agent_positions=[[1, 2], [2, 2], [6, 6]],
        food_map=food_map_with({(1, 1): 4, (2, 3): 2}),
    )
    observations = env.reset_arrays(seed=0)
    assert observations.shape == (3, 3 + 3 + 9 + 9 + 10 + 1)
    first = observations[0]
    np.testing.assert_array_equal(first[:6], [0, 0, 1, 0, 1, 0])  # x = 1, y = 2
    np.testing.assert_array_equal(first[6:15], [-1, -1, -1, 4, 0, 0, 0, 0, 2])  # wall row above
    np.testing.assert_array_equal(first[15:24], [0, 0, 0, 0, 1, 0, 0, 1, 0])  # itself, agent 1 below
    np.testing.assert_array_equal(first[24:34], [0] * 10)  # index 0 in 10 bits
    assert first[34] == 10
    np.testing.assert_array_equal(observations[2][24:34], [0] * 8 + [1, 0])  # index 2
    assert decode_position(observations[2]) == (6, 6)
    np.testing.assert_array_equal(observations[2][6:15], [0, 0, -1, 0, 0, -1, -1, -1, -1])  # corner
    assert all(env.shared_observation_space.contains(obs) for obs in observations)


def test_hidden_position_zeroes_only_the_position_bits():
    kwargs = dict(agent_positions=[[1, 2], [2, 2], [6, 6]], food_map=food_map_with({(1, 1): 4}))
    shown = small_env(**kwargs).reset_arrays(seed=0)
    hidden_env = small_env(observe_position=False, **kwargs)
    hidden = hidden_env.reset_arrays(seed=0)
    assert shown[:, :6].any() and not hidden[:, :6].any()
    np.testing.assert_array_equal(hidden[:, 6:], shown[:, 6:])
    assert all(hidden_env.shared_observation_space.contains(obs) for obs in hidden)


def test_walls_block_moves():
    env = small_env(n_agents=2, agent_positions=[[1, 1], [6, 6]])
    env.reset_arrays(seed=0)
    for actions, expected in [
        ([UP, DOWN], [(1, 1), (6, 6)]),
        ([LEFT, RIGHT], [(1, 1), (6, 6)]),
        ([DOWN, UP], [(2, 1), (5, 6)]),
        ([RIGHT, LEFT], [(2, 2), (5, 5)]),
    ]:
        observations, *_ = env.step_arrays(np.array(actions))
        assert [decode_position(obs) for obs in observations] == expected
        np.testing.assert_array_equal(env.agent_cells(), expected)


def test_lower_index_eats_first_then_stores_and_rewards_update():
    # Agents 0 and 2 share cell (1, 2) holding 3 food; agent 1 waits at (4, 1) next to 4 food on (4, 2).
    env = small_env(
        agent_positions=[[1, 2], [4, 1], [1, 2]],
        food_map=food_map_with({(1, 2): 3, (4, 2): 4, (6, 6): 5}),
    )
    env.reset_arrays(seed=0)
    for _ in range(6):  # everybody pushes against a wall: stores 10 -> 4
        _, rewards, terminated, truncated, info = env.step_arrays(np.array([UP, LEFT, UP]))
        np.testing.assert_allclose(rewards, [0.4] * 3)
        assert not terminated.any() and not truncated.any()
    assert info == {"food_on_map": 12, "mean_store": 4.0}

    observations, _, _, _, info = env.step_arrays(np.array([EAT, RIGHT, EAT]))
    np.testing.assert_array_equal(observations[:, -1], [4 + 2 * 3 - 1, 4 - 1, 4 - 1])  # agent 2 gets nothing
    assert info["food_on_map"] == 9

    observations, rewards, _, _, info = env.step_arrays(np.array([EAT, EAT, EAT]))
    np.testing.assert_array_equal(observations[:, -1], [9 - 1, 3 + 2 * 4 - 1, 3 - 1])
    np.testing.assert_allclose(rewards, [0.4, 0.4, 0.4])
    assert info == {"food_on_map": 5, "mean_store": (8 + 10 + 2) / 3}


def test_store_saturates_and_starvation_reward():
    env = small_env(n_agents=2, agent_positions=[[1, 1], [3, 3]], food_map=food_map_with({(3, 3): 5}))
    env.reset_arrays(seed=0)
    stores, rewards = [], []
    for _ in range(12):
        observations, reward, *_ = env.step_arrays(np.array([UP, EAT]))
        stores.append(observations[:, -1].tolist())
        rewards.append(reward)
    stores, rewards = np.array(stores), np.array(rewards)
    np.testing.assert_array_equal(stores[:, 0], [9, 8, 7, 6, 5, 4, 3, 2, 1, 0, 0, 0])
    np.testing.assert_array_equal(stores[:, 1], [10, 9, 8, 7, 6, 5, 4, 3, 2, 1, 0, 0])  # 10 + 10 - 1 capped
    assert rewards.dtype == np.float32
    np.testing.assert_allclose(rewards[:, 0], [0.4] * 9 + [-0.2] * 3, rtol=1e-6)
    np.testing.assert_allclose(rewards[:, 1], [0.4] * 10 + [-0.2] * 2, rtol=1e-6)


def reference_step(cells: np.ndarray, food: np.ndarray, stores: np.ndarray, actions: np.ndarray, size: int):
    """Loop reference of moves, eating in index order, store update and rewards (no regrowth)."""
    cells, food, stores = cells.copy(), food.copy(), stores.copy()
    steps = [(-1, 0), (1, 0), (0, -1), (0, 1)]
    for agent, action in enumerate(actions):
        x, y = cells[agent]
        if action == EAT:
            stores[agent] += 2 * food[x, y]
            food[x, y] = 0
        else:
            nx, ny = x + steps[action][0], y + steps[action][1]
            if 1 <= nx <= size - 2 and 1 <= ny <= size - 2:
                cells[agent] = nx, ny
    stores = np.clip(stores - 1, 0, 10)
    return cells, food, stores, np.where(stores > 0, 0.4, -0.2)


def test_random_steps_match_loop_reference():
    rng = np.random.default_rng(5)
    size, n_agents = 10, 40
    food = np.zeros((size, size), dtype=np.int64)
    food[1:-1, 1:-1] = rng.integers(0, 6, size=(size - 2, size - 2))
    cells = rng.integers(1, size - 1, size=(n_agents, 2))
    env = surviving_v0.parallel_env(
        n_agents=n_agents, map_size=size, n_resources=0, agent_positions=cells, food_map=food[1:-1, 1:-1]
    )
    env.reset_arrays(seed=0)
    stores = np.full(n_agents, 10)
    for _ in range(40):
        actions = rng.choice(5, size=n_agents, p=[0.15, 0.15, 0.15, 0.15, 0.4])
        cells, food, stores, expected_rewards = reference_step(cells, food, stores, actions, size)
        observations, rewards, *_ = env.step_arrays(actions)
        assert [decode_position(obs, bits=4) for obs in observations] == [tuple(c) for c in cells.tolist()]
        np.testing.assert_array_equal(observations[:, -1], stores)
        np.testing.assert_allclose(rewards, expected_rewards, rtol=1e-6)
        centre = observations[:, 8 + 4]  # food on the own cell, centre of the 3 x 3 window
        np.testing.assert_array_equal(centre, food[cells[:, 0], cells[:, 1]])
        np.testing.assert_array_equal(env.neighbors(), grid_neighbors(cells, 3, 16))


def total_food(env: SurvivingEnv) -> int:
    return int(env.food_grid()[1:-1, 1:-1].sum())


def test_regrowth_only_at_or_below_threshold():
    # One agent: threshold 2 * 1 + 4 = 6. The map holds 7 food, so nothing grows until the agent eats.
    env = small_env(
        n_agents=1,
        map_size=12,
        n_resources=1,
        agent_positions=[[1, 1]],
        resource_positions=[[6, 6]],
        food_map=food_map_with({(1, 1): 1, (1, 3): 1, (10, 10): 5}, map_size=12),
    )
    env.reset_arrays(seed=3)
    reserve = env.resource_reserves()[0]
    for _ in range(5):
        _, _, _, _, info = env.step_arrays(np.array([UP]))
        assert info["food_on_map"] == total_food(env) == 7
    np.testing.assert_array_equal(env.resource_reserves(), [reserve])
    _, _, _, _, info = env.step_arrays(np.array([EAT]))  # 6 left, at the threshold: 1..5 food drops
    grown = info["food_on_map"] - 6
    assert 1 <= grown <= 5
    assert total_food(env) == info["food_on_map"]
    assert env.resource_reserves()[0] == reserve - grown  # the drop lands inside, on an empty cell
    food = env.food_grid()
    food[1, 3] = food[10, 10] = 0
    (new_cell,) = np.argwhere(food > 0)
    assert np.abs(new_cell - 6).max() <= 3


def test_regrowth_stays_interior_and_near_resource_points():
    points = [(1, 1), (8, 8), (1, 8)]
    env = surviving_v0.parallel_env(n_agents=40, map_size=10, n_resources=3, resource_positions=points)
    env.reset_arrays(seed=11)
    reserves_before = env.resource_reserves()
    assert np.all((reserves_before >= 100) & (reserves_before <= 120))
    near_points = np.zeros((10, 10), dtype=bool)
    for x, y in points:
        near_points[max(x - 3, 0) : x + 4, max(y - 3, 0) : y + 4] = True
    for _ in range(12):
        env.step_arrays(np.full(40, UP))
        food = env.food_grid()
        walls = np.ones((10, 10), dtype=bool)
        walls[1:-1, 1:-1] = False
        assert np.all(food[walls] == -1)
        assert food[~walls].min() >= 0 and food.max() <= 5
        assert not np.any(food[~near_points] > 0)
    np.testing.assert_array_equal(env.resource_cells(), points)
    assert total_food(env) > 0
    assert (reserves_before - env.resource_reserves()).sum() >= total_food(env)


def test_regrowth_caps_cells_at_five_and_still_costs_reserve():
    # 200 agents: threshold 404 is above the 64 * 5 food the interior can hold, so food drops every step.
    env = surviving_v0.parallel_env(
        n_agents=200, map_size=10, n_resources=1, resource_positions=[[4, 4]], food_map=np.full((8, 8), 4)
    )
    env.reset_arrays(seed=0)
    _, _, _, _, info = env.step_arrays(np.full(200, UP))
    food = env.food_grid()
    assert food.max() == 5 and np.sum(food == 5) == 1
    assert info["food_on_map"] == 64 * 4 + 1
    assert 100 - 5 <= env.resource_reserves()[0] <= 120 - 1
    for _ in range(30):
        env.step_arrays(np.full(200, UP))
        assert env.food_grid().max() == 5


def test_exhausted_resource_point_moves_with_fresh_reserve():
    env = small_env(
        n_agents=1, map_size=12, n_resources=1, resource_positions=[[6, 6]], agent_positions=[[1, 1]]
    )
    env.reset_arrays(seed=0)
    env._reserves[:] = 1  # about to run out
    env.step_arrays(np.array([UP]))
    assert 100 <= env.resource_reserves()[0] <= 120
    cells_after_relocation = set()
    for seed in range(5):
        env.reset_arrays(seed=seed)
        env._reserves[:] = 1
        env.step_arrays(np.array([UP]))
        cells_after_relocation.add(tuple(env.resource_cells()[0].tolist()))
    assert cells_after_relocation != {(6, 6)}
    assert all(1 <= x <= 10 and 1 <= y <= 10 for x, y in cells_after_relocation)


def test_truncation_at_max_cycles():
    env = surviving_v0.parallel_env(n_agents=4, max_cycles=5)
    env.reset(seed=0)
    for step in range(1, 6):
        _, _, terminations, truncations, infos = env.step({agent: 4 for agent in env.agents})
        assert not any(terminations.values())
        assert all(truncations.values()) == (step == 5)
        assert set(infos["agent_0"]) == {"food_on_map", "mean_store"}
    assert env.agents == []
    with pytest.raises(RuntimeError):
        env.step_arrays(np.zeros(4, dtype=np.int64))


def test_neighbors_use_chebyshev_comm_range():
    env = surviving_v0.parallel_env(n_agents=50, comm_range=3, max_neighbors=8)
    observations = env.reset_arrays(seed=2)
    cells = np.array([decode_position(obs, bits=5) for obs in observations])
    neighbor_lists = env.neighbors()
    np.testing.assert_array_equal(neighbor_lists, grid_neighbors(cells, 3, 8, "chebyshev"))
    np.testing.assert_array_equal(neighbor_lists[:, 0], np.arange(50))


@pytest.mark.parametrize(
    "kwargs",
    [
        dict(n_agents=1025),
        dict(n_agents=9, id_bits=3),
        dict(n_agents=0),
        dict(map_size=3),
        dict(max_cycles=0),
        dict(n_resources=-1),
        dict(comm_range=-1),
        dict(max_neighbors=0),
        dict(render_mode="ansi"),
        dict(n_agents=2, agent_positions=[[1, 1]]),
        dict(n_agents=2, agent_positions=[[1, 1], [0, 5]]),
        dict(n_agents=2, agent_positions=[[1, 1], [5, 31]]),
        dict(n_agents=2, agent_positions=[[1.5, 1], [5, 5]]),
        dict(food_map=np.zeros((32, 32), dtype=np.int64)),
        dict(food_map=np.full((30, 30), 6)),
        dict(food_map=np.full((30, 30), -1)),
        dict(n_resources=2, resource_positions=[[3, 3]]),
        dict(n_resources=1, resource_positions=[[3, 31]]),
    ],
)
def test_invalid_arguments_raise(kwargs):
    with pytest.raises(ValueError):
        surviving_v0.parallel_env(**kwargs)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(id_bits="10"), "id_bits must be an integer in 1..32, got '10'"),
        (dict(map_size="10"), r"map_size must be an integer >= 4 \(a wall ring .*\), got '10'"),
        (dict(max_cycles=5.0), "max_cycles must be an integer >= 1, got 5.0"),
        (dict(n_resources="2"), "n_resources must be an integer >= 0, got '2'"),
        (dict(comm_range="3"), "comm_range must be a number >= 0, got '3'"),
        (dict(max_neighbors=2.5), "max_neighbors must be an integer >= 1, got 2.5"),
        (dict(observe_position="no"), "observe_position must be true or false, got 'no'"),
    ],
)
def test_a_wrongly_typed_argument_names_it_and_its_range(kwargs, message):
    with pytest.raises(ValueError, match=message):
        surviving_v0.parallel_env(**kwargs)


@pytest.mark.parametrize("n_agents", [0, 1025, 2.5, "4"])
def test_the_agent_count_rule_is_stated_once(n_agents):
    """The env and the graph VecEnv built on it state the same valid range."""
    message = f"n_agents must be an integer in 1..1024 .*, got {n_agents!r}"
    with pytest.raises(ValueError, match=message):
        surviving_v0.parallel_env(n_agents=n_agents)
    with pytest.raises(ValueError, match=message):
        make_graph_vec_env("surviving_v0", env_kwargs={"n_agents": n_agents})


def test_one_agent_is_a_graph_env_of_its_own():
    env = make_graph_vec_env("surviving_v0", n_envs=2, env_kwargs={"n_agents": 1, "map_size": 12})
    assert env.reset()["neighbors"].tolist() == [[0] + [-1] * (env.max_neighbors - 1)] * 2


def test_invalid_actions_raise():
    env = small_env()
    env.reset_arrays(seed=0)
    for actions in ([0, 1], [0, 1, 5], [0, -1, 2]):
        with pytest.raises(ValueError):
            env.step_arrays(np.array(actions))


def test_render_rgb_array():
    env = small_env(render_mode="rgb_array", agent_positions=[[1, 1], [1, 1], [6, 6]])
    env.reset_arrays(seed=0)
    image = env.render()
    assert image.shape == (64, 64, 3) and image.dtype == np.uint8
    np.testing.assert_array_equal(image[0, 0], [128, 128, 128])  # wall
    agent_pixel = image[8 + 4, 8 + 4]
    assert agent_pixel[0] > 150 and agent_pixel[1] < 100  # red
    assert not np.array_equal(image[8 + 4, 16 + 4], agent_pixel)  # cell (1, 2) holds no agent


def test_render_without_mode_warns_and_returns_none():
    env = small_env()
    env.reset_arrays(seed=0)
    with pytest.warns(UserWarning):
        assert env.render() is None


def test_render_human_with_dummy_display(monkeypatch):
    pytest.importorskip("pygame")
    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")
    env = small_env(render_mode="human")
    env.reset_arrays(seed=0)
    assert env.render() is None
    env.close()
