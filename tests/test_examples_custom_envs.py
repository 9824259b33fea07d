"""The third-party env examples (examples/battle_magent2.py, examples/spread_mpe2.py): their envs are
built as documented, and each trains and evaluates end to end with tiny settings."""

from __future__ import annotations

import importlib.util
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

from sb3_hgrn import make_graph_vec_env
from tests.doc_snippets import python_block, run_snippet

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def load_example(name: str, needs: str) -> ModuleType:
    """The example script ``examples/<name>.py`` as a module; skips the test without ``needs``."""
    pytest.importorskip(needs)
    spec = importlib.util.spec_from_file_location(name, EXAMPLES / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def assert_nearest_first(lists: np.ndarray, positions: np.ndarray, k: int) -> None:
    """Every row lists the agent itself, then ``k`` others, none farther than an agent left out."""
    distances = np.linalg.norm(positions[:, None] - positions[None], axis=-1)
    assert lists.shape == (len(positions), k + 1)
    for agent, row in enumerate(lists):
        assert row[0] == agent and len(set(row.tolist())) == k + 1 and (row >= 0).all()
        left_out = np.setdiff1d(np.arange(len(positions)), row)
        assert distances[agent, row[1:]].max() <= distances[agent, left_out].min()


def test_battle_red_learns_with_a_graph_of_its_nearest_mates_and_counts_both_sides(tmp_path):
    battle = load_example("battle_magent2", "magent2")
    env = battle.make_env(map_size=18, max_cycles=10)
    env.reset(seed=0)
    grid, (red, blue) = env.unwrapped.env, env.unwrapped.handles
    n_red = len(grid.get_agent_id(red))
    assert env.possible_agents == [f"red_{i}" for i in range(n_red)] and n_red == 6
    assert env.driven_agents == tuple(f"blue_{i}" for i in range(grid.get_num(blue)))
    assert_nearest_first(env.neighbors(), grid.get_pos(red)[np.argsort(grid.get_agent_id(red))], k=4)
    env.step({agent: 0 for agent in env.agents})
    assert env.team_info() == {"red_left": 6, "blue_left": 6}
    grid.add_agents(blue, method="custom", pos=[[9, 9, 0]])  # one more blue agent in the engine only
    assert battle.agents_left(env.env) == {"red_left": 6, "blue_left": 7}

    episodes = battle.main(
        ["--map-size", "18", "--max-cycles", "20", "--copies", "1", "--timesteps", "300",
         "--learning-starts", "100", "--buffer-size", "400", "--eval-episodes", "1", "--save",
         str(tmp_path / "battle.zip")]
    )  # fmt: skip
    for policy in ("random", "soft_hgrn"):
        (episode,) = episodes[policy]
        assert episode["l"] == 20 and 0 <= episode["blue_left"] <= n_red and 0 <= episode["red_left"] <= n_red


def test_battle_blue_learns_with_the_engine_ids_mapped_to_the_wrappers_rows():
    """The custom_envs.md block where blue, listed second in battle's possible_agents, learns: row
    ``k`` of its cells is the engine's cell of ``blue_k``, and the graph is among blue mates."""
    pytest.importorskip("magent2")
    snippet = run_snippet(python_block("custom_envs.md", "def make_blue_env"))
    env = snippet["make_blue_env"](map_size=18, max_cycles=10)
    for seed in (0, 1):
        env.reset(seed=seed)
        env.step({agent: seed for agent in env.agents})
        battle, grid, (_, blue) = env.unwrapped, env.unwrapped.env, env.unwrapped.handles
        assert env.possible_agents == [f"blue_{k}" for k in range(6)] and battle.possible_agents[0] == "red_0"
        cell_of_id = dict(zip(grid.get_agent_id(blue).tolist(), grid.get_pos(blue).tolist(), strict=True))
        expected = np.array(
            [cell_of_id[battle.possible_agents.index(agent)] for agent in env.possible_agents]
        )
        np.testing.assert_array_equal(snippet["blue_cells"](env.env), expected)
        assert_nearest_first(env.neighbors(), expected, k=4)


def test_spread_agents_list_their_nearest_mates_and_report_the_landmarks_covered(tmp_path):
    spread = load_example("spread_mpe2", "mpe2")
    vec_env = make_graph_vec_env(spread.make_env, n_envs=2, seed=0, env_kwargs=dict(n_agents=5, k=2))
    obs = vec_env.reset()
    for copy in range(2):
        world = vec_env.envs[copy].env.unwrapped.world
        positions = np.array([agent.state.p_pos for agent in world.agents])
        assert_nearest_first(obs["neighbors"][copy * 5 : (copy + 1) * 5], positions, k=2)
    assert obs["obs"].shape == (10, 2 + 2 + 2 * 3 + 2 * 3 + 2 * 3)  # 3 mates and 3 landmarks observed

    env = spread.make_env(n_agents=4)
    env.reset(seed=1)
    world = env.unwrapped.world
    world.agents[2].state.p_pos = world.landmarks[0].state.p_pos + 0.05  # 0.07 from landmark 0
    world.agents[3].state.p_pos = world.landmarks[1].state.p_pos + 0.1  # 0.14 from landmark 1
    env.step({agent: 0 for agent in env.agents})  # no action: the agents stay where they are
    landmarks = [landmark.state.p_pos for landmark in world.landmarks]
    nearest = [min(np.linalg.norm(agent.state.p_pos - p) for agent in world.agents) for p in landmarks]
    figures = env.team_info()
    assert figures == {"covered": np.sum(np.less(nearest, 0.1)), "distance": pytest.approx(np.mean(nearest))}
    assert figures["covered"] == 1  # landmark 0 only

    episodes = spread.main(
        ["--agents", "4", "--copies", "1", "--timesteps", "300", "--learning-starts", "100",
         "--eval-episodes", "1", "--save", str(tmp_path / "spread.zip")]
    )  # fmt: skip
    for policy in ("random", "soft_hgrn"):
        (episode,) = episodes[policy]
        assert episode["l"] == 25 and 0 <= episode["covered"] <= 4 and episode["distance"] > 0
