"""TeamFigures: an env's figures after an episode's last step reach info["team_episode"] and
evaluate_team_episodes."""

from __future__ import annotations

import numpy as np
import pytest

from sb3_hgrn import (
    DrivenAgents,
    RandomGraphPolicy,
    TeamFigures,
    evaluate_graph_policy,
    evaluate_team_episodes,
    make_graph_vec_env,
)
from tests.test_driven_agents import TwoTeamsWithGraph


def teams_left(env) -> dict[str, int]:
    """The agents of each team still in the inner env's episode."""
    agents = env.unwrapped.agents
    return {"a_left": sum(a[0] == "a" for a in agents), "b_left": sum(a[0] == "b" for a in agents)}


def make_env(deaths: dict[str, int], max_cycles: int = 6):
    """Team a learns against random b; ``deaths`` maps agents to the step at which they die."""
    inner = TwoTeamsWithGraph(max_cycles=max_cycles, deaths=deaths)
    return TeamFigures(DrivenAgents(inner, "a_"), teams_left)


def test_the_figures_after_the_last_step_reach_the_team_episode():
    deaths = {"b_0": 2, "b_2": 3, "a_1": 4}
    vec_env = make_graph_vec_env(lambda: make_env(deaths), n_envs=2, seed=0)
    vec_env.reset()
    assert vec_env.envs[0].env.team_info() == {}  # nothing after a reset
    for step in range(1, 7):
        _, _, dones, infos = vec_env.step(np.zeros(6, dtype=np.int64))
        assert dones.all() == (step == 6)
        if step == 4:
            assert vec_env.envs[1].env.team_info() == {"a_left": 2, "b_left": 1}
    team = infos[0]["team_episode"]
    assert team["a_left"] == 0 and team["b_left"] == 0  # the time limit took everyone at step 6
    assert team["l"] == 6 and infos[3]["team_episode"]["a_left"] == 0
    assert vec_env.envs[0].env.team_info() == {}  # the copy was reset after its last step

    figures = []
    env = TeamFigures(DrivenAgents(TwoTeamsWithGraph(deaths=deaths), "a_"), lambda e: figures.append(e) or {})
    env.reset(seed=0)
    env.step({agent: 0 for agent in env.agents})
    assert figures == [env.env]  # called once a step with the env given


def test_evaluate_team_episodes_returns_each_episode_with_its_figures():
    # a_0..a_2 all die at step 3, while b_1 still lives: the learners' episode ends there
    deaths = {"a_0": 3, "a_1": 3, "a_2": 3, "b_0": 1, "b_2": 2}
    vec_envs = [make_graph_vec_env(lambda: make_env(deaths), n_envs=2, seed=0) for _ in range(2)]
    episodes = evaluate_team_episodes(RandomGraphPolicy(vec_envs[0], seed=0), vec_envs[0], n_eval_episodes=3)
    assert len(episodes) == 3
    assert [(e["l"], e["a_left"], e["b_left"]) for e in episodes] == [(3, 0, 1)] * 3
    returns, lengths = evaluate_graph_policy(
        RandomGraphPolicy(vec_envs[1], seed=0), vec_envs[1], n_eval_episodes=3, return_episode_rewards=True
    )
    assert returns == [e["r"] for e in episodes] and lengths == [3, 3, 3]


def test_an_env_without_team_info_adds_nothing():
    vec_env = make_graph_vec_env(lambda: DrivenAgents(TwoTeamsWithGraph(max_cycles=2), "a_"), seed=0)
    (episode,) = evaluate_team_episodes(RandomGraphPolicy(vec_env, seed=0), vec_env, n_eval_episodes=1)
    assert set(episode) == {"r", "l", "agents", "final_observation", "terminated"}


@pytest.mark.parametrize(
    "figures, error, match",
    [
        (lambda env: [1, 2], TypeError, "must return a dict of numbers by name, got list"),
        (lambda env: {"left": "many"}, TypeError, r"real numbers by string name, got 'left': str"),
        (lambda env: {3: 1.0}, TypeError, "by string name, got 3"),
        (lambda env: {"r": 1.0}, ValueError, r"names \['r'\], which info\['team_episode'\] holds itself"),
    ],
)
def test_bad_figures_are_refused_at_the_step(figures, error, match):
    vec_env = make_graph_vec_env(lambda: TeamFigures(DrivenAgents(TwoTeamsWithGraph(), "a_"), figures))
    vec_env.reset()
    with pytest.raises(error, match=match):
        vec_env.step(np.zeros(3, dtype=np.int64))


def test_figures_must_be_callable():
    with pytest.raises(TypeError, match="figures must be a callable"):
        TeamFigures(TwoTeamsWithGraph(), {"left": 1})
