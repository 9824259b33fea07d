"""The third-party env examples beside battle and spread (examples/kaz_pettingzoo.py, examples/tag_mpe2.py,
examples/adversarial_pursuit_magent2.py):
their glue builds the env as documented, and every example's config file (examples/configs/) trains its
``ci`` budget through the command line."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from sb3_hgrn import make_graph_vec_env
from sb3_hgrn.cli import main
from sb3_hgrn.experiments.config import resolve_config
from tests.test_examples_custom_envs import EXAMPLES, assert_nearest_first, load_example

CONFIGS = EXAMPLES / "configs"
KAZ_MODULE = "pettingzoo.butterfly.knights_archers_zombies_v11"  # needs pygame
EXAMPLE_PACKAGES = {
    "battle_magent2": "magent2",
    "spread_mpe2": "mpe2",
    "kaz_pettingzoo": KAZ_MODULE,
    "tag_mpe2": "mpe2",
    "adversarial_pursuit_magent2": "magent2",
}


def random_steps(vec_env, n_steps: int) -> None:
    """Step ``vec_env`` ``n_steps`` times with uniformly random actions of every slot."""
    rng = np.random.default_rng(0)
    for _ in range(n_steps):
        vec_env.step(rng.integers(vec_env.action_space.n, size=vec_env.num_envs))


def test_kaz_players_list_their_nearest_fellows_and_the_dead_leave_the_graph():
    kaz = load_example("kaz_pettingzoo", KAZ_MODULE)
    env = kaz.make_env(archers=3, knights=2)
    env.reset(seed=0)
    game = env.unwrapped
    assert env.possible_agents == ["archer_0", "archer_1", "archer_2", "knight_0", "knight_1"]
    corners = np.array([game.agent_map[name].rect.topleft for name in env.possible_agents], dtype=float)
    positions = kaz.player_positions(env.env)
    np.testing.assert_allclose(positions, corners)
    assert_nearest_first(env.neighbors(), positions, k=3)

    game._remove_agent(game.agent_map["archer_1"])  # as a zombie's touch does
    env.step({agent: 5 for agent in env.agents})  # 5: no action
    assert (kaz.player_positions(env.env)[1] == -1000).all()
    assert "archer_1" not in env.agents and env.team_info() == {"players_left": 4}

    vec_env = make_graph_vec_env(kaz.make_env, n_envs=2, seed=0, env_kwargs=dict(archers=2, knights=2))
    obs = vec_env.reset()
    assert obs["obs"].shape == (8, 1 + 2 + 2 + 2 + 10 + 10, 5)  # self, players, swords, arrows, zombies
    random_steps(vec_env, 5)
    vec_env.close()


def test_kaz_observations_stay_in_their_declared_space():
    kaz = load_example("kaz_pettingzoo", KAZ_MODULE)
    from pettingzoo.butterfly.knights_archers_zombies.src.zombie import Zombie

    env = kaz.make_env(archers=1, knights=1)
    env.reset(seed=0)
    game = env.unwrapped
    game.agent_map["archer_0"].rect.y = 0  # an archer at the top, a zombie past the bottom (game over)
    zombie = Zombie(game.np_random)
    zombie.rect.y = 760
    game.zombie_list.add(zombie)
    obs, *_ = env.step({agent: 5 for agent in env.agents})
    assert np.abs(game.observe("archer_0")).max() > 1  # the game's own observation leaves [-1, 1]
    space = env.observation_space("archer_0")
    assert ((space.low <= obs["archer_0"]) & (obs["archer_0"] <= space.high)).all()


def test_tag_predators_learn_the_prey_are_driven_and_every_contact_pays_each_predator():
    tag = load_example("tag_mpe2", "mpe2")
    env = tag.make_env(predators=5, prey=2, observed=3)
    env.reset(seed=0)
    world = env.unwrapped.world
    assert env.possible_agents == [f"adversary_{i}" for i in range(5)]
    assert env.driven_agents == ("agent_0", "agent_1")
    positions = np.array([agent.state.p_pos for agent in world.agents[:5]])
    np.testing.assert_array_equal(tag.predator_positions(env), positions)
    assert_nearest_first(env.neighbors(), positions, k=3)

    prey = world.agents[5].state.p_pos
    for predator, side in zip(world.agents[:2], (-0.03, 0.03), strict=True):  # two on the first prey
        predator.state.p_pos = prey + side
    for far, predator in enumerate(world.agents[2:5]):  # the other predators and prey far away
        predator.state.p_pos = np.array([5.0 + far, 5.0])
    world.agents[6].state.p_pos = np.array([-5.0, -5.0])
    _, rewards, *_ = env.step({agent: 0 for agent in env.agents})  # 0: no action
    assert rewards == {agent: 2 * tag.CONTACT_REWARD for agent in env.possible_agents}  # 2 contacts
    assert "contacts 2.0 per episode" in tag.tag_report([{"r": sum(rewards.values())}], 5)

    vec_env = make_graph_vec_env(tag.make_env, n_envs=2, seed=0, env_kwargs=dict(predators=4, prey=2))
    obs = vec_env.reset()
    assert obs["obs"].shape == (8, 2 + 2 + 2 * 2 + 2 * 4 + 2 * 4)  # 2 obstacles and 4 agents observed
    random_steps(vec_env, 5)
    vec_env.close()


def test_pursuit_predators_learn_with_their_nearest_fellows_and_pay_for_every_tag(tmp_path):
    pursuit = load_example("adversarial_pursuit_magent2", "magent2")
    env = pursuit.make_env(map_size=20, max_cycles=10, k=2)
    env.reset(seed=0)
    grid, (predators, prey) = env.unwrapped.env, env.unwrapped.handles
    ids = grid.get_agent_id(predators)
    assert env.possible_agents == [f"predator_{i}" for i in range(len(ids))] and len(ids) == 5
    assert env.driven_agents == tuple(f"prey_{i}" for i in range(grid.get_num(prey)))
    cells = pursuit.predator_cells(env.env)
    np.testing.assert_array_equal(cells[env.env.learner_rows_of(ids)], grid.get_pos(predators))
    assert_nearest_first(env.neighbors(), cells, k=2)

    _, rewards, *_ = env.step({agent: 0 for agent in env.agents})  # 0: stay
    assert set(rewards.values()) == {0.0}
    tagger = pursuit.make_env(map_size=20, max_cycles=10, tag_penalty=-0.5)
    tagger.reset(seed=0)
    for tag in range(5, 13):  # actions: stay, 4 moves, then 8 tags
        _, rewards, *_ = tagger.step({agent: tag for agent in tagger.agents})
        prey_tagged = np.array(list(rewards.values())) + 0.5  # each tag costs 0.5, each prey hit pays 1
        np.testing.assert_allclose(prey_tagged, np.round(prey_tagged), atol=1e-6)
        assert (prey_tagged > -1e-6).all()

    episodes = pursuit.main(
        ["--map-size", "20", "--max-cycles", "10", "--copies", "1", "--timesteps", "200",
         "--learning-starts", "60", "--eval-episodes", "1", "--save", str(tmp_path / "pursuit.zip")]
    )  # fmt: skip
    assert [episode["l"] for episode in episodes["random"] + episodes["soft_hgrn"]] == [10, 10]
    assert (tmp_path / "pursuit.zip").exists()


@pytest.mark.parametrize("name", sorted(EXAMPLE_PACKAGES))
def test_the_ci_budget_of_every_example_config_trains_through_the_command_line(name, tmp_path):
    pytest.importorskip(EXAMPLE_PACKAGES[name])
    spec, config = f"examples.{name}:make_env", CONFIGS / f"{name}.yml"
    for budget in ("ci", "cpu"):
        assert resolve_config(spec, "soft_hgrn", budget, config_file=config).n_envs >= 1
    args = ["train", "--env", spec, "--config", str(config), "--preset", "soft_hgrn", "--budget", "ci"]
    assert main([*args, "--verbose", "0", "--threads", "1", "--folder", str(tmp_path)]) == 0
    results = json.loads(next(Path(tmp_path).glob("*/soft_hgrn/seed_0/eval.json")).read_text())
    assert results["completed"] and results["n_episodes"] == 1 and results["agent_steps"] >= 200
