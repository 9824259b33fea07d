"""DrivenAgents: one team of a PettingZoo env learns while a controller drives the others."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from pettingzoo import ParallelEnv
from pettingzoo.test import parallel_api_test
from pettingzoo.utils.conversions import parallel_to_aec_wrapper

from sb3_hgrn import DrivenAgents, GraphFromPositions, SoftHGRN, make_graph_vec_env
from sb3_hgrn.common.saved_controllers import ModelController

N = 3  # agents per team
TINY = dict(learning_starts=40, batch_size=8, buffer_size=1000, policy_kwargs=dict(hidden_dim=16), seed=0)


def partner(agent: str) -> str:
    """Agent ``k`` of the other team."""
    return ("b" if agent[0] == "a" else "a") + agent[1:]


class TwoTeams(ParallelEnv):
    """Teams ``a_0..a_{n-1}`` and ``b_0..b_{n-1}``; agent ``k`` observes ``(team, k, t)`` (team 0 for
    ``a``, 1 for ``b``) and picks one of 3 actions. Every agent earns ``10 * own action + its
    partner's action`` (a gone partner's counts 0), so a wrong mapping of actions shows in the rewards.

    ``deaths`` maps agents to the step at which they terminate and leave. The env records the actions
    of every step and refuses actions that are not exactly those of its living agents.
    """

    metadata = {"render_modes": [], "name": "two_teams"}
    OBSERVATION_SPACE = gym.spaces.Box(0.0, 100.0, shape=(3,), dtype=np.float32)
    ACTION_SPACE = gym.spaces.Discrete(3)

    def __init__(self, n: int = N, max_cycles: int = 6, deaths: dict[str, int] | None = None):
        self.possible_agents = [f"a_{k}" for k in range(n)] + [f"b_{k}" for k in range(n)]
        self.agents: list[str] = []
        self.n, self.max_cycles, self.deaths = n, max_cycles, dict(deaths or {})
        self.render_mode = None
        self.recorded: list[dict[str, int]] = []
        self.n_steps = 0

    def observation_space(self, agent):
        return self.OBSERVATION_SPACE

    def action_space(self, agent):
        return self.ACTION_SPACE

    def _observe(self) -> dict[str, np.ndarray]:
        return {
            agent: np.array([agent[0] == "b", int(agent[2:]), self._t], dtype=np.float32)
            for agent in self.agents
        }

    def reset(self, seed=None, options=None):
        self.agents = list(self.possible_agents)
        self._t = 0
        return self._observe(), {agent: {} for agent in self.agents}

    def step(self, actions):
        if sorted(actions) != sorted(self.agents):
            raise ValueError(f"actions for {sorted(actions)}, living agents {self.agents}")
        self.recorded.append(dict(actions))
        self.n_steps += 1
        self._t += 1
        rewards = {agent: 10.0 * actions[agent] + actions.get(partner(agent), 0) for agent in self.agents}
        terminated = {agent: self.deaths.get(agent) == self._t for agent in self.agents}
        truncated = {agent: self._t >= self.max_cycles for agent in self.agents}
        observations = self._observe()
        infos = {agent: {"t": self._t} for agent in self.agents}
        self.agents = [agent for agent in self.agents if not (terminated[agent] or truncated[agent])]
        return observations, rewards, terminated, truncated, infos

    def driven_actions(self, team: str = "b") -> list[dict[str, int]]:
        """The recorded actions of one team, step by step."""
        return [{agent: a for agent, a in step.items() if agent[0] == team} for step in self.recorded]


class TwoTeamsWithGraph(TwoTeams):
    """:class:`TwoTeams` with a graph: agent ``k`` lists itself, its partner and mate ``k + 1`` (mod n)."""

    max_neighbors = 3

    def neighbors(self) -> np.ndarray:
        k = np.arange(self.n)
        team_a = np.stack([k, k + self.n, (k + 1) % self.n], axis=1)
        team_b = np.stack([k + self.n, k, (k + 1) % self.n + self.n], axis=1)
        return np.concatenate([team_a, team_b])


class BoxActionsForB(TwoTeams):
    """:class:`TwoTeams` where team b takes ``Box`` actions."""

    def action_space(self, agent):
        return gym.spaces.Box(-1.0, 1.0, shape=(1,)) if agent[0] == "b" else self.ACTION_SPACE


class Recorder:
    """A model that records what ``predict`` gets; its state counts the steps of the episode and
    agent ``k`` acts ``(k + count) % 3``."""

    def __init__(self, width: int = 3):
        self.observation_space = gym.spaces.Dict(
            {
                "obs": gym.spaces.Box(0.0, 100.0, shape=(3,), dtype=np.float32),
                "neighbors": gym.spaces.Box(-1, 100, shape=(width,), dtype=np.int32),
            }
        )
        self.calls, self.bound, self.seeds = [], [], []

    def bind(self, observation_space, n_agents):
        self.bound.append((observation_space, n_agents))

    def seed(self, seed):
        self.seeds.append(seed)

    def predict(self, observation, state=None, episode_start=None, deterministic=False):
        self.calls.append(
            {
                "obs": observation["obs"].copy(),
                "neighbors": observation["neighbors"].copy(),
                "state": state,
                "episode_start": episode_start.copy(),
                "deterministic": deterministic,
            }
        )
        count = 0 if state is None else state[0] + 1
        return (observation["obs"][:, 1].astype(np.int64) + count) % 3, (count,)


def play(env: DrivenAgents, seed: int | None, n_steps: int = 4, action: int = 1) -> list[tuple]:
    """Reset with ``seed`` and step with every learner taking ``action``; returns every step's dicts."""
    env.reset(seed=seed)
    steps = []
    for _ in range(n_steps):
        if not env.agents:
            break
        steps.append(env.step({agent: action for agent in env.agents}))
    return steps


def test_only_the_learners_are_the_envs_agents():
    inner = TwoTeamsWithGraph()
    env = DrivenAgents(inner, learners="a_")
    assert env.possible_agents == ["a_0", "a_1", "a_2"] and env.driven_agents == ("b_0", "b_1", "b_2")
    observations, infos = env.reset(seed=0)
    assert env.agents == env.possible_agents and set(observations) == set(infos) == set(env.agents)
    np.testing.assert_array_equal(observations["a_2"], [0, 2, 0])
    for result in env.step({agent: 2 for agent in env.agents}):
        assert set(result) == {"a_0", "a_1", "a_2"}
    assert env.observation_space("a_0") == inner.observation_space("a_0") and env.action_space("a_1").n == 3
    with pytest.raises(ValueError, match="'b_0' is not an agent of this env: its agents are the learners"):
        env.observation_space("b_0")
    with pytest.raises(ValueError, match=r"Only learners act .* got actions for \['b_1'\]"):
        env.step({"a_0": 0, "a_1": 0, "a_2": 0, "b_1": 0})
    parallel_api_test(DrivenAgents(TwoTeamsWithGraph(max_cycles=20), learners="b_"), num_cycles=30)


@pytest.mark.parametrize(
    "learners, rows",
    [("b_", [-1, -1, -1, 0, 1, 2]), (["b_0", "a_1"], [-1, 0, -1, 1, -1, -1]), ("a_", [0, 1, 2, -1, -1, -1])],
)
def test_learner_rows_of_maps_inner_indices_to_the_wrappers_agents(learners, rows):
    """The learners listed second (or interleaved) in the inner env's possible_agents: an inner index
    (an engine's agent id where it indexes possible_agents) maps to the learner's row here."""
    inner = TwoTeams()
    env = DrivenAgents(inner, learners=learners)
    np.testing.assert_array_equal(env.learner_rows_of(np.arange(6)), rows)
    for row, agent in enumerate(env.possible_agents):
        assert env.learner_rows_of([inner.possible_agents.index(agent)]).tolist() == [row]
    assert env.learner_rows_of([]).shape == (0,) and env.learner_rows_of(np.array([], dtype=int)).shape == (
        0,
    )
    with pytest.raises(ValueError, match=r"inner_indices must be integers in \[0, 6\).*got \[6\]"):
        env.learner_rows_of([6])
    with pytest.raises(ValueError, match=r"inner_indices must be integers in \[0, 6\).*got \[-1\]"):
        env.learner_rows_of(np.array([-1]))
    with pytest.raises(ValueError, match=r"inner_indices must be integers .*got \[1.5\]"):
        env.learner_rows_of([1.5])


@pytest.mark.parametrize(
    "learners", [["a_0", "a_1", "a_2"], ("a_2", "a_0", "a_1"), "a_", lambda name: name < "b"]
)
def test_learners_as_names_prefix_or_predicate(learners):
    assert DrivenAgents(TwoTeams(), learners).possible_agents == ["a_0", "a_1", "a_2"]


def test_the_learners_graph_is_the_inner_one_cut_down_to_them():
    env = DrivenAgents(TwoTeamsWithGraph(), learners="a_")
    env.reset(seed=0)
    assert env.max_neighbors == 3
    np.testing.assert_array_equal(env.neighbors(), [[0, -1, 1], [1, -1, 2], [2, -1, 0]])
    without = DrivenAgents(TwoTeams(), learners="a_")
    assert getattr(without, "neighbors", None) is None
    with pytest.raises(TypeError, match="GraphFromPositions"):
        make_graph_vec_env(lambda: DrivenAgents(TwoTeams(), learners="a_"))
    positioned = GraphFromPositions(without, positions=lambda env: np.arange(3.0)[:, None], k=1)
    assert make_graph_vec_env(lambda: positioned).num_envs == 3


def test_the_random_controller_repeats_with_the_seed():
    def episode(env, seed):
        env.env.recorded.clear()
        play(env, seed, n_steps=6)
        return env.env.driven_actions()

    env = DrivenAgents(TwoTeams(), learners="a_", controller="random")
    first, again, other = episode(env, 1), episode(env, 1), episode(env, 2)
    assert first == again and first != other
    assert {action for step in first + other for action in step.values()} == {0, 1, 2}
    unseeded = [episode(env, None), episode(env, None)]  # the generator goes on: other episodes
    assert unseeded[0] != unseeded[1]
    assert episode(DrivenAgents(TwoTeams(), "a_"), 1) == first  # a new env with the same seed too


def test_a_function_controller_gets_the_driven_agents_and_its_actions_reach_the_inner_env():
    inner = TwoTeams()
    calls = []

    def mirror(observations, env):
        calls.append(({name: obs.copy() for name, obs in observations.items()}, env))
        return {name: int(obs[1] + obs[2]) % 3 for name, obs in observations.items()}

    env = DrivenAgents(inner, learners="a_", controller=mirror)
    steps = play(env, seed=0, n_steps=3, action=1)
    assert [sorted(seen) for seen, _ in calls] == [["b_0", "b_1", "b_2"]] * 3
    assert all(seen_env is inner for _, seen_env in calls)
    np.testing.assert_array_equal(calls[1][0]["b_2"], [1, 2, 1])  # b_2's observation after step 1
    assert inner.driven_actions() == [{f"b_{k}": (k + t) % 3 for k in range(N)} for t in range(3)]
    # each learner's reward holds its partner's action: 10 * 1 + (k + t) % 3
    for t, (_, rewards, *_) in enumerate(steps):
        assert rewards == {f"a_{k}": 10.0 + (k + t) % 3 for k in range(N)}


def test_a_model_controller_gets_the_driven_graph_and_its_state_is_threaded():
    inner, model = TwoTeamsWithGraph(), Recorder()
    env = DrivenAgents(inner, learners="a_", controller=model, deterministic=True)
    assert [(space.shape, n) for space, n in model.bound] == [((3,), 3)]
    play(env, seed=5, n_steps=3)
    first_seeds = list(model.seeds)
    play(env, seed=5, n_steps=3)
    assert len(model.calls) == 6 and model.seeds[3:] == first_seeds and len(set(first_seeds)) == 3
    for call in model.calls:
        np.testing.assert_array_equal(call["neighbors"], [[0, -1, 1], [1, -1, 2], [2, -1, 0]])
        assert call["neighbors"].dtype == np.int32 and call["deterministic"]
    np.testing.assert_array_equal(model.calls[1]["obs"], [[1, 0, 1], [1, 1, 1], [1, 2, 1]])
    assert [call["state"] for call in model.calls] == [None, (0,), (1,)] * 2
    assert [bool(call["episode_start"].all()) for call in model.calls] == [True, False, False] * 2
    assert [bool(call["episode_start"].any()) for call in model.calls] == [True, False, False] * 2
    assert inner.driven_actions()[:3] == [{f"b_{k}": (k + t) % 3 for k in range(N)} for t in range(3)]


def test_controller_neighbors_give_the_lists_of_the_living_driven_agents():
    given = []

    def ring(env, names):
        given.append(list(names))
        n = len(names)
        return np.stack([np.arange(n), (np.arange(n) - 1) % n], axis=1)

    model = Recorder(width=3)
    env = DrivenAgents(TwoTeams(deaths={"b_1": 1}), "a_", controller=model, controller_neighbors=ring)
    play(env, seed=0, n_steps=2)
    assert given == [["b_0", "b_1", "b_2"], ["b_0", "b_2"]]
    np.testing.assert_array_equal(model.calls[0]["neighbors"], [[0, 2, -1], [1, 0, -1], [2, 1, -1]])
    np.testing.assert_array_equal(model.calls[1]["neighbors"], [[0, 2, -1], [-1, -1, -1], [2, 0, -1]])


def test_a_driven_agent_that_dies_is_not_asked_and_the_model_keeps_its_slot_masked():
    seen = []

    def stay(observations, env):
        seen.append(list(observations))
        return dict.fromkeys(observations, 0)

    inner = TwoTeamsWithGraph(deaths={"b_1": 2})
    env = DrivenAgents(inner, "a_", controller=stay)
    steps = play(env, seed=0, n_steps=4, action=1)
    all_b, without_b_1 = ["b_0", "b_1", "b_2"], ["b_0", "b_2"]
    assert seen == [all_b, all_b, without_b_1, without_b_1]
    assert [sorted(step) for step in inner.driven_actions()] == [all_b, all_b, without_b_1, without_b_1]
    assert steps[2][1]["a_1"] == 10.0  # its partner is gone: only its own action counts
    assert all(len(step[0]) == N for step in steps) and env.agents == ["a_0", "a_1", "a_2"]

    model, inner = Recorder(), TwoTeamsWithGraph(deaths={"b_1": 2})
    play(DrivenAgents(inner, "a_", controller=model), seed=0, n_steps=4)
    assert all(call["obs"].shape == (N, 3) for call in model.calls)
    np.testing.assert_array_equal(model.calls[2]["neighbors"], [[0, -1, -1], [-1, -1, -1], [2, -1, 0]])
    # b_1 keeps the last observation the model had of it (step 1); the others are at step 2
    np.testing.assert_array_equal(model.calls[2]["obs"], [[1, 0, 2], [1, 1, 1], [1, 2, 2]])
    assert sorted(inner.recorded[2]) == ["a_0", "a_1", "a_2", "b_0", "b_2"]


def test_the_episode_goes_on_without_driven_agents_and_ends_with_the_last_learner():
    model = Recorder()
    env = DrivenAgents(TwoTeamsWithGraph(deaths={f"b_{k}": 1 for k in range(N)}), "a_", controller=model)
    steps = play(env, seed=0, n_steps=6)
    assert len(steps) == 6 and len(model.calls) == 1  # asked at step 1 only; the learners play to the end
    assert all(steps[-1][3].values()) and env.agents == []

    inner = TwoTeams(deaths={"a_0": 2, "a_1": 2, "a_2": 2})
    env = DrivenAgents(inner, "a_")
    steps = play(env, seed=0, n_steps=6)
    assert len(steps) == 2 and steps[-1][2] == {"a_0": True, "a_1": True, "a_2": True}
    assert env.agents == [] and inner.agents == ["b_0", "b_1", "b_2"]
    with pytest.raises(RuntimeError, match="No learner is left"):
        env.step({})
    assert inner.n_steps == 2  # not stepped after the learners' end

    vec_env = make_graph_vec_env(lambda: DrivenAgents(TwoTeamsWithGraph(deaths={"a_1": 2}), "a_"), seed=0)
    vec_env.reset()
    dones = [vec_env.step(np.zeros(3, dtype=np.int64))[2] for _ in range(6)]
    assert [bool(done.all()) for done in dones] == [False] * 5 + [True]
    assert vec_env.alive.tolist() == [True, True, True]


def test_an_aec_env_is_converted():
    env = DrivenAgents(parallel_to_aec_wrapper(TwoTeams()), learners="b_")
    assert env.possible_agents == ["b_0", "b_1", "b_2"] and len(play(env, seed=0)) == 4


@pytest.mark.parametrize(
    ("learners", "error", "match"),
    [
        (["a_0", "x_9"], ValueError, r"learners names \['x_9'\], which the env does not have"),
        ("c_", ValueError, r"learners \(the prefix 'c_'\) selects no agent of possible_agents \['a_0'"),
        ([], ValueError, "selects no agent"),
        (lambda name: True, ValueError, "selects every agent, leaving none to drive"),
        (3, TypeError, "learners must be a collection of agent names, a name prefix .* got int"),
    ],
)
def test_bad_learners_are_refused(learners, error, match):
    with pytest.raises(error, match=match):
        DrivenAgents(TwoTeams(), learners)


def test_bad_controllers_are_refused():
    with pytest.raises(ValueError, match="one of \\('random',\\).*loads no saved model.*ModelController"):
        DrivenAgents(TwoTeams(), "a_", controller="chaser")
    with pytest.raises(TypeError, match="controller must be one of .* got int"):
        DrivenAgents(TwoTeams(), "a_", controller=3)
    with pytest.raises(
        ValueError, match="needs the neighbour lists .* TwoTeams has no neighbors\\(\\); pass"
    ):
        DrivenAgents(TwoTeams(), "a_", controller=Recorder())
    with pytest.raises(TypeError, match="controller_neighbors must be a callable"):
        DrivenAgents(TwoTeams(), "a_", controller=Recorder(), controller_neighbors=3)
    with pytest.raises(TypeError, match="draws from Discrete action spaces, but 'b_0' has Box"):
        DrivenAgents(BoxActionsForB(), "a_")
    assert DrivenAgents(BoxActionsForB(), "b_").possible_agents == ["b_0", "b_1", "b_2"]


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        (dict(controller=lambda obs, env: {"b_0": 0}), r"missing \['b_1', 'b_2'\], not driven or gone \[\]"),
        (
            dict(controller=lambda obs, env: {**dict.fromkeys(obs, 0), "a_0": 1}),
            r"not driven or gone \['a_0'\]",
        ),
        (
            dict(controller=lambda obs, env: [0, 0, 0]),
            "must return a dict of actions by agent name, got list",
        ),
        (
            dict(controller=Recorder(), controller_neighbors=lambda env, names: np.zeros((2, 2), int)),
            r"controller_neighbors must return an integer array of shape \(3, K\), got int64 \(2, 2\)",
        ),
        (
            dict(controller=Recorder(), controller_neighbors=lambda env, names: np.full((3, 1), 3)),
            r"controller_neighbors must return agent indices in \[-1, 2\], got 3..3",
        ),
        (
            dict(controller=Recorder(width=2), controller_neighbors=lambda env, names: np.zeros((3, 3), int)),
            "lists of the driven agents are 3 wide, wider than the 2 the controller's model takes",
        ),
    ],
)
def test_bad_controller_output_is_refused_at_the_step(kwargs, match):
    env = DrivenAgents(TwoTeams(), "a_", **kwargs)
    env.reset(seed=0)
    with pytest.raises((ValueError, TypeError), match=match):
        env.step(dict.fromkeys(env.agents, 0))
    assert env.env.n_steps == 0


def make_team_a_env(controller="random", **kwargs) -> DrivenAgents:
    """Team a learns on :class:`TwoTeamsWithGraph`."""
    return DrivenAgents(TwoTeamsWithGraph(), learners="a_", controller=controller, **kwargs)


@pytest.fixture(scope="module")
def team_a_model(tmp_path_factory):
    """A SoftHGRN trained 300 agent-steps on team a against random b, saved; its path."""
    model = SoftHGRN("GraphPolicy", make_graph_vec_env(make_team_a_env, n_envs=2, seed=0), **TINY)
    model.learn(300)
    path = tmp_path_factory.mktemp("models") / "team_a.zip"
    model.save(path)
    return path


def test_self_play_a_saved_model_of_team_a_drives_team_b(team_a_model):
    controller = ModelController(team_a_model)
    env = make_team_a_env(controller, deterministic=True)
    assert isinstance(controller.model, SoftHGRN) and controller.model.policy.n_agents == N
    play(env, seed=0, n_steps=4)
    # the same model, given team b's observations and graph, acts as the env's controller did
    replay, state = ModelController(team_a_model), None
    graph = np.array([[0, -1, 1], [1, -1, 2], [2, -1, 0]], dtype=np.int32)
    for t, driven in enumerate(env.env.driven_actions()):
        obs = np.array([[1, k, t] for k in range(N)], dtype=np.float32)
        actions, state = replay.predict(
            {"obs": obs, "neighbors": graph},
            state=state,
            episode_start=np.full(N, t == 0),
            deterministic=True,
        )
        assert driven == {f"b_{k}": int(actions[k]) for k in range(N)}

    sampling = make_team_a_env(ModelController(team_a_model))
    episodes = []
    for _ in range(2):
        sampling.env.recorded.clear()
        play(sampling, seed=4, n_steps=6)
        episodes.append(sampling.env.driven_actions())
    assert episodes[0] == episodes[1]


class CountingController(ModelController):
    """A ModelController that counts its predictions."""

    n_predictions = 0

    def predict(self, *args, **kwargs):
        self.n_predictions += 1
        return super().predict(*args, **kwargs)


def test_the_wrapped_env_trains_also_against_the_model_being_trained():
    model = SoftHGRN("GraphPolicy", make_graph_vec_env(make_team_a_env, n_envs=2, seed=0), **TINY)
    model.learn(200)
    assert model.num_timesteps >= 200
    opponent = CountingController(model)  # self-play: the model being trained drives team b
    model.set_env(make_graph_vec_env(make_team_a_env, n_envs=2, seed=1, env_kwargs={"controller": opponent}))
    model.learn(200, reset_num_timesteps=False)
    assert model.num_timesteps >= 400 and opponent.n_predictions >= 200 // (2 * N)
