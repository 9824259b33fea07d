import numpy as np
import pytest
from pettingzoo.test import parallel_api_test

from sb3_hgrn.envs import ctc_v0
from sb3_hgrn.envs.ctc_v0 import TreasureCollectionEnv

UP, DOWN, LEFT, RIGHT, STAY, COLLECT, DUMP = range(7)  # x - 1, x + 1, y - 1, y + 1, ...
HUNTER_CHANNELS = ("hunters", "red_banks", "blue_banks", "red_resources", "blue_resources", "red", "blue")
BANK_CHANNELS = ("hunters", "banks", "resources", "treasure", "carried")


def small_env(**kwargs) -> TreasureCollectionEnv:
    """A 12 x 12 map (interior 3..8) with 3 hunters, 2 + 2 banks and no resource points unless given."""
    defaults = dict(
        n_hunters=3,
        n_red_banks=2,
        n_blue_banks=2,
        map_size=12,
        n_red_resources=0,
        n_blue_resources=0,
        comm_range=2,
        max_neighbors=7,
    )
    return ctc_v0.parallel_env(**{**defaults, **kwargs})


def treasure_map(cells_and_items: dict[tuple[int, int], int], map_size: int = 12) -> np.ndarray:
    """Interior treasure map ``(map_size - 6, map_size - 6)`` with items on the given ``(x, y)`` cells."""
    treasure = np.zeros((map_size - 6, map_size - 6), dtype=np.int64)
    for (x, y), items in cells_and_items.items():
        treasure[x - 3, y - 3] = items
    return treasure


def decode_position(observation: np.ndarray) -> tuple[int, int]:
    powers = 2 ** np.arange(6, -1, -1)
    return int(observation[:7] @ powers), int(observation[7:14] @ powers)


def window(observation: np.ndarray, channel: int) -> np.ndarray:
    """The 7 x 7 window of one channel, indexed ``[dx + 3, dy + 3]``."""
    return observation[14 + 49 * channel : 14 + 49 * (channel + 1)].reshape(7, 7)


def test_parallel_api():
    env = ctc_v0.parallel_env(n_hunters=4, n_red_banks=2, n_blue_banks=3, map_size=16, max_cycles=30)
    parallel_api_test(env, num_cycles=40)


def test_groups_spaces_and_agent_order():
    env = ctc_v0.parallel_env()
    assert [group.name for group in env.groups] == ["hunter", "red_bank", "blue_bank"]
    assert env.possible_agents[:2] == ["hunter_0", "hunter_1"]
    assert env.possible_agents[19:22] == ["hunter_19", "red_bank_0", "red_bank_1"]
    assert env.possible_agents[30:] == [f"blue_bank_{i}" for i in range(10)]
    np.testing.assert_array_equal(env.group_ids, [0] * 20 + [1] * 10 + [2] * 10)
    assert env.group_ids.dtype == np.int64
    for agent, obs_dim, n_actions, group in [
        ("hunter_3", 359, 7, 0),
        ("red_bank_9", 259, 5, 1),
        ("blue_bank_0", 259, 5, 2),
    ]:
        assert env.observation_space(agent).shape == (obs_dim,)
        assert env.observation_space(agent).dtype == np.int8
        assert env.action_space(agent).n == n_actions
        assert env.observation_space(agent) is env.groups[group].observation_space
    shared = env.shared_observation_space
    assert shared.shape == (359,) and shared.dtype == np.int8
    assert env.shared_action_space.n == 7
    # The padded space covers both groups: hunters' bounds throughout, banks' within their first 259.
    np.testing.assert_array_equal(shared.high[357:], [5, 5])
    assert shared.low[14 + 3 * 49] == -1 and shared.high[14 + 3 * 49] == 127  # bank treasure, red resources
    assert shared.low.min() == -1 and shared.high.max() == 127

    observations = env.reset_arrays(seed=0)
    assert observations.shape == (40, 359) and observations.dtype == np.int8
    assert not observations[20:, 259:].any()
    assert all(env.shared_observation_space.contains(obs) for obs in observations)
    dict_observations, _ = env.reset(seed=0)
    assert dict_observations["hunter_0"].shape == (359,)
    assert dict_observations["blue_bank_9"].shape == (259,)
    assert all(env.observation_space(agent).contains(obs) for agent, obs in dict_observations.items())


@pytest.mark.parametrize("n_hunters", [1, 7, 60])
def test_other_hunter_counts_keep_observation_sizes(n_hunters):
    env = ctc_v0.parallel_env(n_hunters=n_hunters, n_red_banks=3, n_blue_banks=4)
    observations = env.reset_arrays(seed=1)
    assert observations.shape == (n_hunters + 7, 359)
    assert env.observation_space("hunter_0").shape == (359,)
    assert env.observation_space("blue_bank_3").shape == (259,)
    assert env.regrowth_threshold == 2 * n_hunters
    observations, rewards, *_ = env.step_arrays(np.full(n_hunters + 7, STAY))
    assert observations.shape == (n_hunters + 7, 359) and rewards.shape == (n_hunters + 7,)


def test_position_encodes_x_and_y():
    env = small_env(
        map_size=40,
        hunter_positions=[[5, 9], [9, 5], [5, 10]],
        red_bank_positions=[[36, 3], [20, 33]],
        blue_bank_positions=[[3, 36], [3, 3]],
    )
    observations = env.reset_arrays(seed=0)
    assert [decode_position(obs) for obs in observations] == [
        (5, 9), (9, 5), (5, 10), (36, 3), (20, 33), (3, 36), (3, 3)
    ]  # fmt: skip
    assert not np.array_equal(observations[0][:14], observations[1][:14])  # x and y swapped
    np.testing.assert_array_equal(observations[0][:7], observations[2][:7])  # same x, y differs
    assert not np.array_equal(observations[0][7:14], observations[2][7:14])
    observations, *_ = env.step_arrays(np.array([RIGHT, DOWN, LEFT, UP, STAY, LEFT, STAY]))
    assert [decode_position(obs) for obs in observations] == [
        (5, 10), (10, 5), (5, 9), (35, 3), (20, 33), (3, 35), (3, 3)
    ]  # fmt: skip


def test_observation_windows_on_hand_built_state():
    env = small_env(
        n_hunters=3,
        hunter_positions=[[4, 4], [4, 4], [5, 6]],
        red_bank_positions=[[4, 5], [3, 3]],
        blue_bank_positions=[[6, 4], [8, 8]],
        n_red_resources=1,
        red_resource_positions=[[5, 5]],
        n_blue_resources=2,
        blue_resource_positions=[[3, 4], [3, 4]],
        red_treasure=treasure_map({(4, 4): 2, (6, 6): 5}),
        blue_treasure=treasure_map({(4, 4): 3, (7, 4): 1}),
    )
    observations = env.reset_arrays(seed=0)
    hunter = observations[0]
    expected = {name: np.zeros((7, 7), dtype=np.int64) for name in HUNTER_CHANNELS}
    expected["hunters"][3, 3], expected["hunters"][4, 5] = 2, 1
    expected["red_banks"][3, 4] = expected["red_banks"][2, 2] = 1
    expected["blue_banks"][5, 3] = 1  # (8, 8) is out of the window
    expected["red_resources"][4, 4] = 1
    expected["blue_resources"][2, 3] = 2
    for colour, items in (("red", {(4, 4): 2, (6, 6): 5}), ("blue", {(4, 4): 3, (7, 4): 1})):
        expected[colour][:2, :] = expected[colour][:, :2] = -1  # walls: x or y in {1, 2}
        for (x, y), count in items.items():
            expected[colour][x - 1, y - 1] = count
    for channel, name in enumerate(HUNTER_CHANNELS):
        np.testing.assert_array_equal(window(hunter, channel), expected[name], err_msg=name)
    np.testing.assert_array_equal(hunter[357:], [0, 0])
    np.testing.assert_array_equal(observations[1], hunter)  # same cell, nothing carried

    observations, *_ = env.step_arrays(np.array([COLLECT, STAY, STAY, STAY, STAY, STAY, STAY]))
    np.testing.assert_array_equal(observations[0][357:], [2, 3])
    blue_bank = observations[5]  # at (6, 4): the hunters' cell (4, 4) is at offset (-2, 0)
    assert decode_position(blue_bank) == (6, 4)
    assert not blue_bank[259:].any()
    bank = dict(zip(BANK_CHANNELS, (window(blue_bank, channel) for channel in range(5)), strict=True))
    assert bank["hunters"][1, 3] == 2 and bank["hunters"].sum() == 3
    assert bank["banks"][3, 3] == 1 and bank["banks"].sum() == 1  # itself; red banks are not shown
    assert bank["resources"][0, 3] == 2 and bank["resources"].sum() == 2
    assert bank["treasure"][1, 3] == 0 and bank["treasure"][4, 3] == 1  # blue picked up at (4, 4)
    np.testing.assert_array_equal(bank["treasure"][:, :2], -1)  # y <= 2 is wall
    np.testing.assert_array_equal(bank["treasure"][6], -1)  # x = 9 is wall
    assert bank["carried"][1, 3] == 3 and bank["carried"].sum() == 3  # blue carried by hunter 0
    red_bank = observations[3]  # at (4, 5)
    assert window(red_bank, 3)[3, 2] == 0 and window(red_bank, 3)[5, 4] == 5  # red: (4, 4) empty now
    assert window(red_bank, 4)[3, 2] == 2  # red carried on (4, 4)


def test_collect_cap_red_first_and_lowest_index_first():
    # Hunter 0 alone on B = (6, 6); hunters 1, 2, 3 share A = (4, 4); hunter 3 does not collect.
    env = small_env(
        n_hunters=4,
        hunter_positions=[[6, 6], [4, 4], [4, 4], [4, 4]],
        red_treasure=treasure_map({(4, 4): 3, (6, 6): 5, (6, 4): 4}),
        blue_treasure=treasure_map({(4, 4): 4, (6, 6): 2, (6, 4): 4}),
    )
    env.reset_arrays(seed=0)
    observations, rewards, _, _, info = env.step_arrays(
        np.array([COLLECT, COLLECT, COLLECT, STAY] + [STAY] * 4)
    )
    np.testing.assert_array_equal(env.carried(), [[5, 0], [3, 2], [0, 2], [0, 0]])
    np.testing.assert_array_equal(observations[:4, 357:], env.carried())
    assert rewards.dtype == np.float32
    np.testing.assert_allclose(rewards, [0.99, 0.99, 0.39] + [-0.01] * 5, rtol=1e-6)
    treasure = env.treasure_grid()
    np.testing.assert_array_equal(treasure[:, 4, 4], [0, 0])
    np.testing.assert_array_equal(treasure[:, 6, 6], [0, 2])
    assert info == {
        "collected": 12,
        "delivered_red": 0,
        "delivered_blue": 0,
        "treasure_on_map": 10,
        "carried": 12,
    }

    # Full load: nothing taken. Hunter 2 (capacity 3) moves to (6, 4), then takes 3 of 4 red.
    _, rewards, _, _, _ = env.step_arrays(np.array([COLLECT, STAY, DOWN, STAY] + [STAY] * 4))
    np.testing.assert_allclose(rewards[:3], [-0.01, -0.01, -0.01], rtol=1e-6)
    env.step_arrays(np.array([STAY, STAY, DOWN, STAY] + [STAY] * 4))
    _, rewards, _, _, info = env.step_arrays(np.array([COLLECT, STAY, COLLECT, STAY] + [STAY] * 4))
    np.testing.assert_array_equal(env.carried()[[0, 2]], [[5, 0], [3, 2]])
    np.testing.assert_allclose(rewards[[0, 2]], [-0.01, -0.01 + 0.6], rtol=1e-6)
    np.testing.assert_array_equal(env.treasure_grid()[:, 6, 4], [1, 4])
    assert info["collected"] == 15 and info["treasure_on_map"] == 7


def test_dump_delivers_to_banks_in_3x3_and_splits_among_them():
    env = small_env(
        hunter_positions=[[4, 4], [7, 7], [3, 8]],
        red_bank_positions=[[5, 5], [4, 4]],  # both within the 3 x 3 around hunter 0
        blue_bank_positions=[[4, 6], [8, 8]],  # (4, 6) is 2 cells from hunter 0; (8, 8) next to hunter 1
        red_treasure=treasure_map({(4, 4): 3, (3, 8): 1}),
        blue_treasure=treasure_map({(4, 4): 2, (7, 7): 4}),
    )
    env.reset_arrays(seed=0)
    _, rewards, *_ = env.step_arrays(np.array([COLLECT, COLLECT, COLLECT, STAY, STAY, STAY, STAY]))
    np.testing.assert_allclose(rewards, [0.99, 0.79, 0.19, -0.01, -0.01, -0.01, -0.01], rtol=1e-6)
    np.testing.assert_array_equal(env.carried(), [[3, 2], [0, 4], [1, 0]])

    # Red bank 0 moves away in the same step: banks move after the hunters, so it still gets its share.
    _, rewards, _, _, info = env.step_arrays(np.array([DUMP, DUMP, DUMP, DOWN, STAY, STAY, STAY]))
    np.testing.assert_allclose(rewards, [2.99, 3.99, -0.01, 1.49, 1.49, -0.01, 3.99], rtol=1e-6)
    np.testing.assert_array_equal(env.carried(), [[0, 2], [0, 0], [1, 0]])  # no red bank near hunter 2
    assert (info["delivered_red"], info["delivered_blue"], info["carried"]) == (3, 4, 3)
    assert tuple(env.agent_cells()[3]) == (6, 5)


def test_bank_near_several_dumping_hunters_gets_the_sum_of_its_shares():
    # Blue bank 0 at (4, 6) is next to both hunters; blue bank 1 at (5, 7) only to hunter 1.
    env = small_env(
        n_hunters=2,
        hunter_positions=[[4, 5], [5, 6]],
        red_bank_positions=[[8, 3], [8, 3]],
        blue_bank_positions=[[4, 6], [5, 7]],
        blue_treasure=treasure_map({(4, 5): 2, (5, 6): 3}),
    )
    env.reset_arrays(seed=0)
    env.step_arrays(np.array([COLLECT, COLLECT, STAY, STAY, STAY, STAY]))
    _, rewards, _, _, info = env.step_arrays(np.array([DUMP, DUMP, STAY, STAY, STAY, STAY]))
    # Hunter 0: 2 items, k = 1; hunter 1: 3 items, k = 2 (1.5 each).
    np.testing.assert_allclose(rewards, [1.99, 2.99, -0.01, -0.01, 3.49, 1.49], rtol=1e-6)
    assert (info["delivered_red"], info["delivered_blue"], info["carried"]) == (0, 5, 0)


def reference_step(cells, group_ids, treasure, carried, actions, size):
    """Loop reference of one step without regrowth: hunters in index order, then all moves."""
    cells, treasure, carried = cells.copy(), treasure.copy(), carried.copy()
    rewards = np.full(len(cells), -0.01)
    for hunter in range(len(carried)):
        x, y = cells[hunter]
        if actions[hunter] == COLLECT:
            for colour in (0, 1):
                items = min(treasure[colour, x, y], 5 - carried[hunter].sum())
                treasure[colour, x, y] -= items
                carried[hunter, colour] += items
                rewards[hunter] += 0.2 * items
        elif actions[hunter] == DUMP:
            for colour in (0, 1):
                near = [
                    bank
                    for bank in range(len(carried), len(cells))
                    if group_ids[bank] == colour + 1 and np.abs(cells[bank] - cells[hunter]).max() <= 1
                ]
                if near and carried[hunter, colour]:
                    items = carried[hunter, colour]
                    rewards[hunter] += items
                    for bank in near:
                        rewards[bank] += items / len(near)
                    carried[hunter, colour] = 0
    steps = [(-1, 0), (1, 0), (0, -1), (0, 1)]
    for agent, action in enumerate(actions):
        if action < 4:
            target = cells[agent] + steps[action]
            if 3 <= target.min() and target.max() <= size - 4:
                cells[agent] = target
    return cells, treasure, carried, rewards


def test_random_steps_match_loop_reference():
    rng = np.random.default_rng(5)
    size, n_hunters = 12, 30
    treasure = np.full((2, size, size), -1)
    treasure[:, 3:-3, 3:-3] = rng.integers(0, 6, size=(2, size - 6, size - 6))
    env = ctc_v0.parallel_env(
        n_hunters=n_hunters,
        n_red_banks=4,
        n_blue_banks=3,
        map_size=size,
        n_red_resources=0,
        n_blue_resources=0,
        red_treasure=treasure[0, 3:-3, 3:-3],
        blue_treasure=treasure[1, 3:-3, 3:-3],
    )
    env.reset_arrays(seed=0)
    cells, carried = env.agent_cells(), np.zeros((n_hunters, 2), dtype=np.int64)
    for _ in range(40):
        hunter_actions = rng.choice(7, size=n_hunters, p=[0.1, 0.1, 0.1, 0.1, 0.1, 0.3, 0.2])
        actions = np.concatenate([hunter_actions, rng.integers(0, 5, size=7)])
        cells, treasure, carried, expected_rewards = reference_step(
            cells, env.group_ids, treasure, carried, actions, size
        )
        observations, rewards, _, _, info = env.step_arrays(actions)
        assert [decode_position(obs) for obs in observations] == [tuple(c) for c in cells.tolist()]
        np.testing.assert_array_equal(observations[:n_hunters, 357:], carried)
        np.testing.assert_array_equal(env.treasure_grid(), treasure)
        np.testing.assert_allclose(rewards, expected_rewards, rtol=1e-5, atol=1e-6)
        red_centre = observations[:n_hunters, 14 + 5 * 49 + 24]  # red treasure on the own cell
        np.testing.assert_array_equal(red_centre, treasure[0][cells[:n_hunters, 0], cells[:n_hunters, 1]])
        assert info["treasure_on_map"] == treasure[:, 3:-3, 3:-3].sum()
        assert info["carried"] == carried.sum()
    assert info["collected"] > 0 and info["delivered_red"] > 0 and info["delivered_blue"] > 0


def test_regrowth_per_colour_below_threshold():
    # One hunter: threshold 2. Red starts with 2 items (no regrowth), blue with 3.
    env = small_env(
        n_hunters=1,
        map_size=20,
        hunter_positions=[[3, 3]],
        n_red_resources=1,
        red_resource_positions=[[10, 10]],
        n_blue_resources=1,
        blue_resource_positions=[[5, 14]],
        red_treasure=treasure_map({(3, 3): 1, (16, 16): 1}, map_size=20),
        blue_treasure=treasure_map({(16, 3): 3}, map_size=20),
    )
    env.reset_arrays(seed=3)
    reserves = env.resource_reserves()
    assert np.all((reserves >= 100) & (reserves <= 120))
    for _ in range(3):
        _, _, _, _, info = env.step_arrays(np.array([STAY, STAY, STAY, STAY, STAY]))
        assert info["treasure_on_map"] == 5
    np.testing.assert_array_equal(env.resource_reserves(), reserves)
    _, _, _, _, info = env.step_arrays(np.array([COLLECT, STAY, STAY, STAY, STAY]))  # red: 1 left < 2
    grown = info["treasure_on_map"] - 4
    assert 1 <= grown <= 3  # the drop always lands inside: (10, 10) +- 5 is interior
    np.testing.assert_array_equal(env.resource_reserves(), reserves - [grown, 0])
    red = env.treasure_grid()[0]
    red[16, 16] = 0
    (new_cell,) = np.argwhere(red > 0)
    assert np.abs(new_cell - 10).max() <= 5 and red[tuple(new_cell)] == grown
    np.testing.assert_array_equal(env.treasure_grid()[1][3:-3, 3:-3], treasure_map({(16, 3): 3}, map_size=20))


def test_regrowth_stays_interior_near_points_and_caps_cells():
    # 50 hunters: threshold 100; points in opposite corners, next to the walls.
    env = ctc_v0.parallel_env(
        n_hunters=50,
        map_size=30,
        n_red_resources=2,
        red_resource_positions=[[3, 3], [3, 3]],
        n_blue_resources=1,
        blue_resource_positions=[[26, 26]],
    )
    env.reset_arrays(seed=11)
    reserves_before = env.resource_reserves()
    walls = np.ones((30, 30), dtype=bool)
    walls[3:-3, 3:-3] = False
    for _ in range(40):
        env.step_arrays(np.full(env.n_agents, STAY))
    treasure = env.treasure_grid()
    assert np.all(treasure[:, walls] == -1)
    assert treasure[:, ~walls].min() >= 0 and treasure.max() == 5
    assert treasure[0, 9:, :].max() <= 0 and treasure[0, :, 9:].max() <= 0  # red within 5 of (3, 3)
    assert treasure[1, :21, :].max() <= 0 and treasure[1, :, :21].max() <= 0  # blue within 5 of (26, 26)
    spent = reserves_before - env.resource_reserves()
    assert spent[:2].sum() >= treasure[0, ~walls].sum() > 0 and spent[2] >= treasure[1, ~walls].sum() > 0


def test_exhausted_resource_point_moves_with_fresh_reserve():
    # (8, 8) +- 5 lies inside the interior 3..14, so the first drop always costs reserve.
    env = ctc_v0.parallel_env(
        n_hunters=100, map_size=18, n_red_resources=1, n_blue_resources=0, red_resource_positions=[[8, 8]]
    )
    moved_to = set()
    for seed in range(4):
        env.reset_arrays(seed=seed)
        env._reserves[:] = 1
        observations, *_ = env.step_arrays(np.full(env.n_agents, STAY))
        assert 100 <= env.resource_reserves()[0] <= 120
        cell = env.resource_cells()[0]
        moved_to.add(tuple(cell.tolist()))
        # The hunters' red-resource channel shows the point at its new cell, and only there.
        for observation, offset in zip(observations[:100], cell - env.agent_cells()[:100], strict=True):
            resources = window(observation, 3)
            in_window = np.abs(offset).max() <= 3
            assert resources.sum() == in_window and (not in_window or resources[tuple(offset + 3)] == 1)
    assert moved_to != {(8, 8)} and all(3 <= x <= 14 and 3 <= y <= 14 for x, y in moved_to)


def run_episode(env: TreasureCollectionEnv, seed: int | None, n_steps: int = 40):
    observations = [env.reset_arrays(seed=seed)]
    rewards, neighbor_lists = [], []
    action_rng = np.random.default_rng(123)
    n_actions = np.where(env.group_ids == 0, 7, 5)
    for _ in range(n_steps):
        obs, reward, _, _, _ = env.step_arrays((action_rng.random(env.n_agents) * n_actions).astype(np.int64))
        observations.append(obs)
        rewards.append(reward)
        neighbor_lists.append(env.neighbors())
    return np.array(observations), np.array(rewards), np.array(neighbor_lists)


def test_same_seed_gives_identical_episodes_and_unseeded_resets_continue():
    env_a, env_b = ctc_v0.parallel_env(), ctc_v0.parallel_env()
    first_a, first_b = run_episode(env_a, seed=7), run_episode(env_b, seed=7)
    for array_a, array_b in zip(first_a, first_b, strict=True):
        np.testing.assert_array_equal(array_a, array_b)
    assert first_a[1].max() > 0  # something was collected or delivered
    assert not np.array_equal(run_episode(env_a, seed=8)[0], first_a[0])
    second_a = run_episode(env_a, seed=None)
    assert not np.array_equal(second_a[0], first_a[0])
    run_episode(env_b, seed=8)
    np.testing.assert_array_equal(run_episode(env_b, seed=None)[0], second_a[0])


def brute_force_neighbors(cells: np.ndarray, radius: int, width: int) -> np.ndarray:
    rows = np.full((len(cells), width), -1)
    for i in range(len(cells)):
        distances = np.abs(cells - cells[i]).max(axis=1)
        ranked = sorted(
            (0 if j == i else 1 + distances[j], j) for j in range(len(cells)) if distances[j] <= radius
        )
        kept = [j for _, j in ranked[:width]]
        rows[i, : len(kept)] = kept
    return rows


@pytest.mark.parametrize("n_hunters, max_neighbors", [(20, 24), (60, 24), (60, 120)])
def test_graph_links_all_groups_within_chebyshev_5(n_hunters, max_neighbors):
    env = ctc_v0.parallel_env(n_hunters=n_hunters, map_size=24, max_neighbors=max_neighbors)
    env.reset_arrays(seed=4)
    for _ in range(3):
        neighbor_lists = env.neighbors()
        assert neighbor_lists.shape == (env.n_agents, max_neighbors) and neighbor_lists.dtype == np.int64
        np.testing.assert_array_equal(neighbor_lists[:, 0], np.arange(env.n_agents))
        np.testing.assert_array_equal(
            neighbor_lists, brute_force_neighbors(env.agent_cells(), 5, max_neighbors)
        )
        linked_groups = env.group_ids[neighbor_lists[neighbor_lists >= 0]]
        assert set(linked_groups.tolist()) == {0, 1, 2}
        env.step_arrays(np.zeros(env.n_agents, dtype=np.int64) + DOWN)


def test_truncation_and_team_info_through_dict_api():
    env = ctc_v0.parallel_env(n_hunters=4, n_red_banks=1, n_blue_banks=1, max_cycles=5)
    env.reset(seed=0)
    for step in range(1, 6):
        _, rewards, terminations, truncations, infos = env.step({agent: STAY for agent in env.agents})
        assert not any(terminations.values())
        assert all(truncations.values()) == (step == 5)
        assert set(infos["red_bank_0"]) == {
            "collected",
            "delivered_red",
            "delivered_blue",
            "treasure_on_map",
            "carried",
        }
        assert rewards["blue_bank_0"] == pytest.approx(-0.01)
    assert env.agents == []
    with pytest.raises(RuntimeError):
        env.step_arrays(np.zeros(6, dtype=np.int64))


@pytest.mark.parametrize(
    "kwargs",
    [
        dict(n_hunters=0),
        dict(n_red_banks=0),
        dict(n_blue_banks=-1),
        dict(map_size=7),
        dict(map_size=129),
        dict(max_cycles=0),
        dict(n_red_resources=-1),
        dict(n_blue_resources=-1),
        dict(comm_range=-1),
        dict(max_neighbors=0),
        dict(render_mode="ansi"),
        dict(n_hunters=2, hunter_positions=[[3, 3]]),
        dict(n_hunters=2, hunter_positions=[[3, 3], [2, 5]]),
        dict(n_hunters=2, hunter_positions=[[3, 3], [5, 37]]),
        dict(n_hunters=2, hunter_positions=[[3.5, 3], [5, 5]]),
        dict(n_red_banks=1, red_bank_positions=[[40, 5]]),
        dict(n_blue_banks=1, blue_bank_positions=[[5, 5], [6, 6]]),
        dict(n_red_resources=1, red_resource_positions=[[0, 0]]),
        dict(n_blue_resources=2, blue_resource_positions=[[5, 5]]),
        dict(red_treasure=np.zeros((40, 40), dtype=np.int64)),
        dict(blue_treasure=np.full((34, 34), 6)),
        dict(red_treasure=np.full((34, 34), -1)),
    ],
)
def test_invalid_arguments_raise(kwargs):
    with pytest.raises(ValueError):
        ctc_v0.parallel_env(**kwargs)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(n_hunters="4"), "n_hunters must be an integer >= 1, got '4'"),
        (dict(n_red_banks=2.5), "n_red_banks must be an integer >= 1, got 2.5"),
        (dict(n_blue_banks=True), "n_blue_banks must be an integer >= 1, got True"),
        (dict(n_blue_banks=0), "n_blue_banks must be an integer >= 1, got 0"),
        (dict(map_size="40"), r"map_size must be an integer in 8..128 \(a 3-cell wall ring .*\), got '40'"),
        (dict(map_size=129), r"map_size must be an integer in 8..128 \(.*\), got 129"),
        (dict(max_cycles=10.0), "max_cycles must be an integer >= 1, got 10.0"),
        (dict(n_red_resources="5"), "n_red_resources must be an integer >= 0, got '5'"),
        (dict(n_blue_resources=-1), "n_blue_resources must be an integer >= 0, got -1"),
        (dict(comm_range="5"), "comm_range must be a number >= 0, got '5'"),
        (dict(max_neighbors=2.0), "max_neighbors must be an integer >= 1, got 2.0"),
    ],
)
def test_a_wrongly_typed_or_out_of_range_argument_names_it_and_its_range(kwargs, message):
    with pytest.raises(ValueError, match=message):
        ctc_v0.parallel_env(**kwargs)


def test_numpy_integers_are_integers():
    env = ctc_v0.parallel_env(n_hunters=np.int64(3), n_red_banks=np.int32(1), map_size=np.int64(12))
    assert env.n_agents == 3 + 1 + 10


def test_invalid_actions_raise():
    env = small_env()
    env.reset_arrays(seed=0)
    env.step_arrays(np.array([6, 5, 0, 4, 3, 2, 1]))
    for actions in (
        [0, 1, 2, 3, 4, 0],
        [7, 0, 0, 0, 0, 0, 0],
        [0, 0, 0, 5, 0, 0, 0],
        [0, 0, 0, 0, 0, 0, 6],
        [-1] * 7,
    ):
        with pytest.raises(ValueError):
            env.step_arrays(np.array(actions))
    with pytest.raises(ValueError):
        env.step_arrays(np.zeros(7))  # floats


def test_render_rgb_array():
    env = small_env(
        render_mode="rgb_array",
        hunter_positions=[[3, 3], [3, 3], [8, 8]],
        red_bank_positions=[[4, 3], [4, 3]],
        blue_bank_positions=[[5, 3], [5, 3]],
        red_treasure=treasure_map({(3, 4): 5}),
    )
    env.reset_arrays(seed=0)
    image = env.render()
    assert image.shape == (96, 96, 3) and image.dtype == np.uint8
    np.testing.assert_array_equal(image[0, 0], [128, 128, 128])  # wall
    hunter_pixel, red_bank_pixel, blue_bank_pixel = (
        image[24 + 4, 24 + 4],
        image[32 + 1, 24 + 1],
        image[40 + 1, 24 + 1],
    )
    assert hunter_pixel[1] > 100 and hunter_pixel[0] < 50 and hunter_pixel[2] < 50
    assert red_bank_pixel[0] > 200 and red_bank_pixel[2] < 100
    assert blue_bank_pixel[2] > 200 and blue_bank_pixel[0] < 100
    treasure_pixel = image[24 + 4, 32 + 4]
    assert treasure_pixel[0] == 255 and treasure_pixel[1] < 100  # red tint


def test_render_without_mode_warns_and_human_mode_with_dummy_display(monkeypatch):
    env = small_env()
    env.reset_arrays(seed=0)
    with pytest.warns(UserWarning):
        assert env.render() is None
    pytest.importorskip("pygame")
    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")
    env = small_env(render_mode="human")
    env.reset_arrays(seed=0)
    assert env.render() is None
    env.close()
