import gymnasium as gym
import numpy as np
import pytest
from pettingzoo import ParallelEnv
from pettingzoo.utils.conversions import aec_to_parallel_wrapper, parallel_to_aec_wrapper

from sb3_hgrn import GraphFromPositions, SoftHGRN, make_graph_vec_env
from sb3_hgrn.envs import surviving_v0
from sb3_hgrn.envs.position_graph import PositionGraph


def brute_force(points, k=None, radius=None, max_neighbors=None, world_size=None):
    """Reference neighbour lists: every pair's distance, each row sorted by (distance, index)."""
    points = np.asarray(points, dtype=np.float64)
    n = len(points)
    offsets = np.abs(points[None, :, :] - points[:, None, :])
    if world_size is not None:
        offsets = np.minimum(offsets, world_size - offsets)
    distances = np.sqrt((offsets**2).sum(axis=-1))
    width = k + 1 if k is not None else max_neighbors if radius is not None else n
    lists = np.full((n, width), -1)
    for i in range(n):
        others = [j for j in range(n) if j != i and (radius is None or distances[i, j] <= radius)]
        row = [i] + sorted(others, key=lambda j: (distances[i, j], j))
        lists[i, : min(width, len(row))] = row[:width]
    return lists


def uniform_points(n_agents, dim, seed=0):
    return np.random.default_rng(seed).random((n_agents, dim)) * 10


@pytest.mark.parametrize("dim", [1, 2, 3])
@pytest.mark.parametrize("k", [1, 4, 9])
def test_k_nearest_match_brute_force(dim, k):
    points = uniform_points(60, dim, seed=k)
    np.testing.assert_array_equal(PositionGraph(60, k=k).neighbors(points), brute_force(points, k=k))


@pytest.mark.parametrize("dim", [1, 2, 3])
def test_radius_with_cap_matches_brute_force(dim):
    points = uniform_points(80, dim, seed=dim)
    radius = {1: 0.3, 2: 1.5, 3: 2.5}[dim]
    lists = PositionGraph(80, radius=radius, max_neighbors=6).neighbors(points)
    np.testing.assert_array_equal(lists, brute_force(points, radius=radius, max_neighbors=6))
    listed = (lists >= 0).sum(axis=1)
    assert listed.min() < 6 and listed.max() == 6  # some rows are cut to the cap, some are not full


def test_full_graph_matches_brute_force_and_k_of_all_others():
    points = uniform_points(30, 2)
    graph = PositionGraph(30)
    assert graph.max_neighbors == 30
    np.testing.assert_array_equal(graph.neighbors(points), brute_force(points))
    np.testing.assert_array_equal(graph.neighbors(points), PositionGraph(30, k=29).neighbors(points))


@pytest.mark.parametrize("dim", [1, 2, 3])
def test_torus_matches_brute_force_on_wrapped_positions(dim):
    sides = np.array([10.0, 6.0, 8.0][:dim])
    shifts = np.array([-20.0, 6.0, 16.0][:dim])  # whole sides: the same points on the torus
    points = uniform_points(50, dim, seed=3) * sides / 10 + shifts
    wrapped = np.mod(points, sides)
    for graph, expected in [
        (PositionGraph(50, k=5, world_size=sides), brute_force(wrapped, k=5, world_size=sides)),
        (
            PositionGraph(50, radius=1.2, max_neighbors=5, world_size=sides),
            brute_force(wrapped, radius=1.2, max_neighbors=5, world_size=sides),
        ),
    ]:
        np.testing.assert_array_equal(graph.neighbors(points), expected)


def test_torus_links_agents_across_the_edge():
    points = np.array([[0.1, 5.0], [9.9, 5.0], [5.0, 5.0]])
    np.testing.assert_array_equal(
        PositionGraph(3, k=1, world_size=10.0).neighbors(points)[:2], [[0, 1], [1, 0]]
    )
    np.testing.assert_array_equal(PositionGraph(3, k=1).neighbors(points)[:2], [[0, 2], [1, 2]])


def test_k_at_least_the_other_agents_lists_all_and_pads():
    points = uniform_points(4, 2)
    lists = PositionGraph(4, k=6).neighbors(points)
    assert lists.shape == (4, 7)
    np.testing.assert_array_equal(lists, brute_force(points, k=6))
    assert (lists[:, 4:] == -1).all() and (np.sort(lists[:, :4], axis=1) == np.arange(4)).all()


def test_no_neighbour_within_radius_lists_only_the_agent():
    points = np.arange(5.0)[:, None] * 10
    lists = PositionGraph(5, radius=9.0, max_neighbors=3).neighbors(points)
    np.testing.assert_array_equal(lists, np.stack([np.arange(5), -np.ones(5), -np.ones(5)], axis=1))


def test_radius_is_inclusive_and_ties_go_to_the_lower_index():
    cells = np.stack(np.meshgrid(np.arange(3.0), np.arange(3.0), indexing="ij"), axis=-1).reshape(-1, 2)
    lists = PositionGraph(9, radius=1.0, max_neighbors=5).neighbors(cells)
    np.testing.assert_array_equal(lists[4], [4, 1, 3, 5, 7])  # the centre: four neighbours at distance 1
    np.testing.assert_array_equal(lists, brute_force(cells, radius=1.0, max_neighbors=5))


def test_agents_at_one_point_list_themselves_first():
    # Which of the agents at one distance fill a row is unspecified; each is listed once, in index order.
    lists = PositionGraph(5, k=2).neighbors(np.zeros((5, 2)))
    np.testing.assert_array_equal(lists[:, 0], np.arange(5))
    assert (lists[:, 1] < lists[:, 2]).all() and (lists[:, 1:] != lists[:, :1]).all() and (lists >= 0).all()
    np.testing.assert_array_equal(
        PositionGraph(5, radius=1.0, max_neighbors=1).neighbors(np.zeros((5, 2))), [[0], [1], [2], [3], [4]]
    )


def test_a_gone_agent_takes_no_place_in_a_list():
    points = np.array([[0.0, 0.0], [0.1, 0.0], [1.0, 0.0], [5.0, 5.0]])
    alive = np.array([True, False, True, True])
    np.testing.assert_array_equal(
        PositionGraph(4, k=1).neighbors(points, alive), [[0, 2], [1, -1], [2, 0], [3, 2]]
    )
    # Radius mode, rows full: the gone agent 1 is the nearest of 0 and 2 and still takes no place.
    np.testing.assert_array_equal(
        PositionGraph(4, radius=2.0, max_neighbors=2).neighbors(points, alive),
        [[0, 2], [1, -1], [2, 0], [3, -1]],
    )


@pytest.mark.parametrize("kwargs", [dict(k=3), dict(radius=2.0, max_neighbors=4), dict()])
def test_living_agents_are_linked_as_if_the_gone_ones_were_not_there(kwargs):
    points = uniform_points(40, 2, seed=5)
    alive = np.random.default_rng(5).random(40) < 0.6
    living = np.flatnonzero(alive)
    points[~alive] = np.nan  # never read
    lists = PositionGraph(40, **kwargs).neighbors(points, alive)
    expected = brute_force(points[living], **kwargs)
    width = lists.shape[1]
    np.testing.assert_array_equal(lists[living, : expected.shape[1]], np.append(living, -1)[expected])
    assert (lists[living, expected.shape[1] :] == -1).all()
    np.testing.assert_array_equal(
        lists[~alive], np.pad(np.flatnonzero(~alive)[:, None], ((0, 0), (0, width - 1)), constant_values=-1)
    )


def test_no_living_agent_lists_each_agent_alone():
    lists = PositionGraph(3, k=2).neighbors(np.full((3, 2), np.nan), np.zeros(3, dtype=bool))
    np.testing.assert_array_equal(lists, [[0, -1, -1], [1, -1, -1], [2, -1, -1]])


@pytest.mark.parametrize("alive", [np.ones(3, dtype=bool), np.ones(4), [1, 0, 1, 1]])
def test_bad_alive_is_rejected(alive):
    with pytest.raises(ValueError, match=r"alive must be a bool array of shape \(n_agents=4,\)"):
        PositionGraph(4, k=1).neighbors(np.zeros((4, 2)), alive)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        (dict(k=0), "k must be a positive integer"),
        (dict(k=2.5), "k must be a positive integer"),
        (dict(k=True), "k must be a positive integer"),
        (dict(k=2, radius=1.0, max_neighbors=3), "not both"),
        (dict(radius=-1.0, max_neighbors=3), "radius must be a finite number >= 0"),
        (dict(radius=float("nan"), max_neighbors=3), "radius must be a finite number >= 0"),
        (dict(radius=float("inf"), max_neighbors=3), "radius must be a finite number >= 0"),
        (dict(radius="1", max_neighbors=3), "radius must be a finite number >= 0"),
        (dict(radius=1.0), "radius needs max_neighbors"),
        (dict(radius=1.0, max_neighbors=0), "radius needs max_neighbors"),
        (dict(k=2, max_neighbors=3), "max_neighbors is the list width of radius mode"),
        (dict(max_neighbors=3), "max_neighbors is the list width of radius mode"),
        (dict(k=2, world_size=0.0), "world_size must be a positive side"),
        (dict(k=2, world_size=[[1.0, 2.0]]), "world_size must be a positive side"),
        (dict(k=2, world_size=[]), "world_size must be a positive side"),
    ],
)
def test_bad_arguments_are_rejected(kwargs, message):
    with pytest.raises(ValueError, match=message):
        PositionGraph(4, **kwargs)
    with pytest.raises(ValueError, match=message):
        GraphFromPositions(SwarmEnv(4), SwarmEnv.positions, **kwargs)


def test_bad_agent_count_is_rejected():
    with pytest.raises(ValueError, match="n_agents must be a positive integer"):
        PositionGraph(0, k=1)


@pytest.mark.parametrize(
    ("points", "world_size", "message"),
    [
        (np.zeros((3, 2)), None, r"shape \(n_agents=4, dim\)"),
        (np.zeros(4), None, r"shape \(n_agents=4, dim\)"),
        (np.zeros((4, 0)), None, r"shape \(n_agents=4, dim\)"),
        (np.full((4, 2), np.nan), None, "positions must be finite"),
        (np.array([["a", "b"]] * 4), None, "real numbers"),
        (np.zeros((4, 3)), [1.0, 2.0], "world_size has 2 sides for positions of dim 3"),
    ],
)
def test_bad_positions_are_rejected(points, world_size, message):
    with pytest.raises(ValueError, match=message):
        PositionGraph(4, k=1, world_size=world_size).neighbors(points)


class SwarmEnv(ParallelEnv):
    """A third-party-style env without a graph: agents at float positions in the unit square.

    Actions move an agent by 0.1 (stay, +x, -x, +y, -y); it earns 1 at each step it ends within 0.25
    of the centre. Observation: its position ``(2,)``.
    """

    metadata = {"render_modes": [], "name": "swarm"}

    def __init__(self, n_agents: int = 6, max_cycles: int = 10):
        self.possible_agents = [f"bird_{i}" for i in range(n_agents)]
        self.max_cycles = max_cycles
        self.render_mode = None
        self.xy = np.zeros((n_agents, 2))
        self._rng = np.random.default_rng()

    @staticmethod
    def positions(env: "SwarmEnv") -> np.ndarray:
        return env.xy

    def observation_space(self, agent):
        return gym.spaces.Box(0.0, 1.0, shape=(2,), dtype=np.float32)

    def action_space(self, agent):
        return gym.spaces.Discrete(5)

    def _observations(self):
        return {agent: self.xy[i].astype(np.float32) for i, agent in enumerate(self.agents)}

    def reset(self, seed=None, options=None):
        if seed is not None:
            self._rng = np.random.default_rng(seed)
        self.agents = list(self.possible_agents)
        self.xy = self._rng.random((len(self.agents), 2))
        self._t = 0
        return self._observations(), {agent: {} for agent in self.agents}

    def step(self, actions):
        moves = np.array([[0, 0], [1, 0], [-1, 0], [0, 1], [0, -1]]) * 0.1
        self.xy = np.clip(self.xy + moves[[actions[agent] for agent in self.agents]], 0.0, 1.0)
        self._t += 1
        near_centre = np.linalg.norm(self.xy - 0.5, axis=1) <= 0.25
        observations = self._observations()
        rewards = {agent: float(near_centre[i]) for i, agent in enumerate(self.agents)}
        done = self._t >= self.max_cycles
        terminations = {agent: False for agent in self.agents}
        truncations = {agent: done for agent in self.agents}
        infos = {agent: {} for agent in self.agents}
        if done:
            self.agents = []
        return observations, rewards, terminations, truncations, infos


def test_wrapper_builds_the_graph_once_per_step_from_the_given_env():
    seen = []
    env = SwarmEnv(5)
    wrapped = GraphFromPositions(env, lambda e: seen.append(e) or e.xy, radius=0.4, max_neighbors=3)
    assert wrapped.max_neighbors == 3 and wrapped.possible_agents == env.possible_agents
    wrapped.reset(seed=0)
    first = wrapped.neighbors()
    assert wrapped.neighbors() is first and not first.flags.writeable and seen == [env]
    np.testing.assert_array_equal(first, brute_force(env.xy, radius=0.4, max_neighbors=3))
    wrapped.step({agent: 1 for agent in wrapped.agents})
    np.testing.assert_array_equal(wrapped.neighbors(), brute_force(env.xy, radius=0.4, max_neighbors=3))
    assert len(seen) == 2


class MortalSwarmEnv(SwarmEnv):
    """A SwarmEnv whose agent ``bird_1`` dies at the first step and is dropped from ``agents``; its
    position is then ``nan`` (the env no longer knows it)."""

    def step(self, actions):
        result = super().step(actions)
        if "bird_1" in self.agents:
            self.agents.remove("bird_1")
        self.xy[1] = np.nan
        return result


def test_wrapper_links_only_the_agents_still_in_the_env():
    env = MortalSwarmEnv(4)
    wrapped = GraphFromPositions(env, SwarmEnv.positions, k=1)
    wrapped.reset(seed=0)
    env.xy[:] = [[0.0, 0.0], [0.1, 0.0], [1.0, 0.0], [5.0, 5.0]]
    np.testing.assert_array_equal(wrapped.neighbors(), [[0, 1], [1, 0], [2, 1], [3, 2]])
    wrapped.step({agent: 0 for agent in wrapped.agents})
    env.xy[[0, 2, 3]] = [[0.0, 0.0], [1.0, 0.0], [5.0, 5.0]]
    np.testing.assert_array_equal(wrapped.neighbors(), [[0, 2], [1, -1], [2, 0], [3, 2]])


def test_graph_vec_env_links_the_living_around_a_dead_agent():
    vec_env = make_graph_vec_env(
        lambda: GraphFromPositions(MortalSwarmEnv(5), SwarmEnv.positions, k=2), seed=0
    )
    vec_env.reset()
    obs = vec_env.step(np.zeros(5, dtype=int))[0]
    xy = vec_env.envs[0].env.xy
    living = np.array([0, 2, 3, 4])
    expected = np.full((5, 3), -1)
    expected[living] = np.append(living, -1)[brute_force(xy[living], k=2)]
    np.testing.assert_array_equal(obs["neighbors"], expected)


def test_wrapper_rejects_what_is_not_a_positions_callable_or_an_env():
    with pytest.raises(TypeError, match="positions must be a callable"):
        GraphFromPositions(SwarmEnv(), np.zeros((6, 2)), k=2)
    with pytest.raises(TypeError, match="PettingZoo ParallelEnv or AEC env"):
        GraphFromPositions(gym.make("CartPole-v1"), SwarmEnv.positions, k=2)


def test_graph_vec_env_observes_the_wrapped_graph():
    vec_env = make_graph_vec_env(
        lambda: GraphFromPositions(SwarmEnv(6), SwarmEnv.positions, k=3), n_envs=2, seed=1
    )
    obs = vec_env.reset()
    assert obs["neighbors"].shape == (12, 4) and obs["obs"].shape == (12, 2)
    for copy in range(2):
        xy = vec_env.envs[copy].env.xy
        np.testing.assert_array_equal(obs["neighbors"][copy * 6 : (copy + 1) * 6], brute_force(xy, k=3))
        np.testing.assert_allclose(obs["obs"][copy * 6 : (copy + 1) * 6], xy, rtol=1e-6)


def test_wrapped_third_party_env_trains_with_soft_hgrn():
    vec_env = make_graph_vec_env(
        lambda: GraphFromPositions(SwarmEnv(6), SwarmEnv.positions, radius=0.5, max_neighbors=4),
        n_envs=2,
        seed=0,
    )
    model = SoftHGRN("GraphPolicy", vec_env, learning_starts=96, batch_size=4, train_freq=1,
                     policy_kwargs=dict(hidden_dim=16, n_heads=2), seed=0)  # fmt: skip
    model.learn(480)
    assert model.num_timesteps == 480 and model._n_updates > 0
    actions, _ = model.predict(vec_env.reset(), deterministic=True)
    assert actions.shape == (12,)


def test_make_graph_vec_env_takes_an_env_instance_for_one_copy():
    wrapped = GraphFromPositions(SwarmEnv(4), SwarmEnv.positions, k=1)
    vec_env = make_graph_vec_env(wrapped, seed=0)
    assert vec_env.envs[0].env is wrapped and vec_env.reset()["neighbors"].shape == (4, 2)
    with pytest.raises(ValueError, match=r"makes one copy .* pass a callable"):
        make_graph_vec_env(wrapped, n_envs=2)
    with pytest.raises(ValueError, match="takes no env_kwargs"):
        make_graph_vec_env(wrapped, env_kwargs={"n_agents": 4})


def test_make_graph_vec_env_takes_an_env_module():
    vec_env = make_graph_vec_env(surviving_v0, env_kwargs={"n_agents": 5, "map_size": 8})
    assert vec_env.n_agents == 5


def test_parallelizable_aec_env_is_converted_and_turn_based_is_refused():
    aec = parallel_to_aec_wrapper(SwarmEnv(4))  # an AEC env, not the wrapper pettingzoo unwraps again
    seen = []
    wrapped = GraphFromPositions(aec, lambda env: seen.append(env) or env.unwrapped.xy, k=2)
    assert isinstance(wrapped.env, aec_to_parallel_wrapper)
    vec_env = make_graph_vec_env(wrapped, seed=0)
    obs = vec_env.reset()
    np.testing.assert_array_equal(obs["neighbors"], brute_force(aec.unwrapped.xy, k=2))
    vec_env.step(np.zeros(4, dtype=int))
    assert seen == [aec, aec]  # positions() gets the env as given, not its parallel conversion
    aec.metadata = {**aec.metadata, "is_parallelizable": False}
    with pytest.raises(TypeError, match="is_parallelizable=True"):
        make_graph_vec_env(aec)


def test_env_without_graph_points_to_graph_from_positions():
    with pytest.raises(TypeError, match="GraphFromPositions"):
        make_graph_vec_env(SwarmEnv)
