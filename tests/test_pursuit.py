import itertools

import numpy as np
import pytest
from pettingzoo.test import parallel_api_test

from sb3_hgrn import SoftHGRN, make_graph_vec_env
from sb3_hgrn.common.saved_controllers import ModelController
from sb3_hgrn.envs import pursuit_v0
from sb3_hgrn.envs.pursuit_v0 import PursuitEnv, evader_actions

STAY = {"predator": 2, "prey": 4}
PREY_MOVES = [(a % 3 - 1, a // 3 - 1) for a in range(9)]  # prey action -> (dx, dy)


def small_env(**kwargs) -> PursuitEnv:
    """A 16 x 16 map: 3 predators, 6 prey."""
    return pursuit_v0.parallel_env(**{"map_size": 16, "max_cycles": 40, **kwargs})


def run_episode(env: PursuitEnv, seed: int | None, n_steps: int = 30):
    observations = [env.reset_arrays(seed=seed)]
    rewards, neighbor_lists, cells = [], [], [env.prey_cells().copy()]
    action_rng = np.random.default_rng(123)
    for _ in range(n_steps):
        obs, reward, _, _, _ = env.step_arrays(
            action_rng.integers(0, env.shared_action_space.n, env.n_agents)
        )
        observations.append(obs)
        rewards.append(reward)
        neighbor_lists.append(env.neighbors())
        cells.append(env.prey_cells().copy())
    return np.array(observations), np.array(rewards), np.array(neighbor_lists), np.array(cells)


def test_parallel_api():
    parallel_api_test(small_env(max_cycles=15), num_cycles=20)
    parallel_api_test(small_env(max_cycles=15, learners="prey"), num_cycles=20)


def test_paper_size_spaces_and_agent_counts():
    env = pursuit_v0.parallel_env()
    observations = env.reset_arrays(seed=0)
    assert env.possible_agents == [f"predator_{i}" for i in range(25)]
    assert observations.shape == (25, 500) and observations.dtype == np.uint8
    assert set(np.unique(observations)) <= {0, 1}
    space = env.shared_observation_space
    assert (
        space.shape == (500,) and space.dtype == np.uint8 and space.low.max() == 0 and space.high.min() == 1
    )
    assert env.shared_action_space.n == 13 and env.action_space("predator_3").n == 13
    assert env.prey_cells().shape == (50, 2) and env.predator_cells().shape == (25, 2)
    assert env.max_neighbors == 16 and env.max_cycles == 500

    prey = pursuit_v0.parallel_env(learners="prey")
    observations = prey.reset_arrays(seed=0)
    assert prey.possible_agents == [f"prey_{i}" for i in range(50)]
    assert observations.shape == (50, 405) and observations.dtype == np.uint8
    assert prey.shared_observation_space.shape == (405,) and prey.shared_action_space.n == 9


def test_same_seed_gives_identical_episodes_and_unseeded_resets_continue():
    env_a, env_b = small_env(prey_controller="random"), small_env(prey_controller="random")
    first_a, first_b = run_episode(env_a, seed=7), run_episode(env_b, seed=7)
    for array_a, array_b in zip(first_a, first_b, strict=True):
        np.testing.assert_array_equal(array_a, array_b)
    assert not np.array_equal(run_episode(env_a, seed=8)[3], first_a[3])
    second_a = run_episode(env_a, seed=None)
    assert not np.array_equal(second_a[3], first_a[3])
    run_episode(env_b, seed=8)
    np.testing.assert_array_equal(run_episode(env_b, seed=None)[3], second_a[3])


def test_truncation_at_max_cycles_and_no_step_after_the_end():
    env = small_env(max_cycles=5)
    with pytest.raises(RuntimeError):
        env.step_arrays(np.zeros(env.n_agents, dtype=np.int64))  # before the first reset
    env.reset(seed=0)
    for step in range(1, 6):
        _, rewards, terminations, truncations, infos = env.step(dict.fromkeys(env.agents, 5))
        assert not any(terminations.values())
        assert all(truncations.values()) == (step == 5) and any(truncations.values()) == (step == 5)
        assert set(infos["predator_0"]) == {"tags", "tag_attempts", "episode_tags"}
        assert all(isinstance(reward, float) for reward in rewards.values())
    assert env.agents == []
    with pytest.raises(RuntimeError, match="outside an episode"):
        env.step_arrays(np.zeros(env.n_agents, dtype=np.int64))
    env.reset_arrays(seed=1)
    env.step_arrays(np.zeros(env.n_agents, dtype=np.int64))  # a reset starts a new episode


def brute_force_neighbors(cells: np.ndarray, radius: float, width: int) -> np.ndarray:
    rows = np.full((len(cells), width), -1)
    for i, cell in enumerate(cells):
        squared = ((cells - cell) ** 2).sum(axis=1)
        others = [
            j for j in np.lexsort((np.arange(len(cells)), squared)) if j != i and squared[j] <= radius**2
        ]
        row = [i, *others][:width]
        rows[i, : len(row)] = row
    return rows


@pytest.mark.parametrize("learners", ["predator", "prey"])
def test_graph_is_self_first_and_within_euclidean_range(learners):
    env = pursuit_v0.parallel_env(learners=learners, comm_range=6, max_neighbors=8)
    env.reset_arrays(seed=3)
    rng = np.random.default_rng(0)
    for _ in range(3):
        cells = env.agent_cells()
        neighbor_lists = env.neighbors()
        np.testing.assert_array_equal(neighbor_lists[:, 0], np.arange(env.n_agents))
        np.testing.assert_array_equal(neighbor_lists, brute_force_neighbors(cells, 6, 8))
        assert (neighbor_lists[:, 1:] >= 0).any()
        env.step_arrays(rng.integers(0, env.shared_action_space.n, env.n_agents))


def test_cells_follow_magent_coordinates():
    """A predator's cell is the top-left cell of its 2 x 2 body; x is the view's column, y its row."""
    env = small_env(map_size=30)
    observations = env.reset_arrays(seed=5)
    views = observations.reshape(-1, 10, 10, 5)
    assert views[:, 4:6, 4:6, 1].all()  # own body, own-team channel
    prey, seen = env.prey_cells(), 0
    for view, (x, y) in zip(views, env.predator_cells(), strict=True):
        for prey_x, prey_y in prey:
            row, column = prey_y - y + 4, prey_x - x + 4
            if 0 <= row < 10 and 0 <= column < 10 and (row - 4.5) ** 2 + (column - 4.5) ** 2 < 25:
                assert view[row, column, 3] == 1
                seen += 1
    assert seen > 0


def test_rewards_count_tags_and_tag_penalty():
    env = small_env(map_size=20, max_cycles=100, prey_controller="random", tag_penalty=-0.5)
    env.reset_arrays(seed=2)
    rng = np.random.default_rng(1)
    total_tags = 0
    for _ in range(100):
        actions = rng.integers(0, 13, env.n_agents)
        _, rewards, _, _, info = env.step_arrays(actions)
        assert rewards.dtype == np.float32 and rewards.shape == (5,)
        assert info["tag_attempts"] == np.count_nonzero(actions >= 5)
        np.testing.assert_allclose(rewards.sum(), info["tags"] - 0.5 * info["tag_attempts"], rtol=1e-5)
        np.testing.assert_array_equal(rewards[actions < 5], 0)
        total_tags += info["tags"]
        assert info["episode_tags"] == total_tags
    assert total_tags > 0


def reference_evader(prey_cells, predator_cells, walls):
    """Loop reference: squared distances to the nearest body cell by brute force."""

    def distance(cell, corner):
        return min(
            (cell[0] - corner[0] - dx) ** 2 + (cell[1] - corner[1] - dy) ** 2
            for dx in (0, 1)
            for dy in (0, 1)
        )

    actions = []
    for cell in prey_cells:
        nearest = min(range(len(predator_cells)), key=lambda j: (distance(cell, predator_cells[j]), j))
        scores = []
        for dx, dy in PREY_MOVES:
            target = (cell[0] + dx, cell[1] + dy)
            scores.append(-1 if walls[target] else distance(target, predator_cells[nearest]))
        actions.append(int(np.argmax(scores)))
    return np.array(actions)


def test_evader_moves_away_from_the_nearest_predator():
    walls = np.zeros((9, 9), dtype=bool)
    walls[[0, -1], :] = walls[:, [0, -1]] = True
    walls[6, 2] = True
    predators = np.array([[2, 2], [5, 5]])  # bodies x 2..3, y 2..3 and x 5..6, y 5..6
    prey = np.array([[5, 2], [7, 7], [5, 1], [1, 6]])
    # (5, 2): body 0 is nearest (2 against 3); (6, 2) is a wall, the farthest free cell is (6, 1):
    #   move (+1, -1), action 2.
    # (7, 7): body 1 is nearest (sqrt 2), every cell farther away is a wall: it stays, action 4.
    # (5, 1): body 0 is nearest; (6, 0) is the border, (6, 1) is farthest: move (+1, 0), action 5.
    # (1, 6): body 0 is nearest (sqrt 10 against 4); x = 0 is the border, (1, 7) at sqrt 17 beats
    #   (2, 7) at 4: move (0, +1), action 7.
    np.testing.assert_array_equal(evader_actions(prey, predators, walls), [2, 4, 5, 7])
    np.testing.assert_array_equal(reference_evader(prey, predators, walls), [2, 4, 5, 7])

    rng = np.random.default_rng(0)
    walls = rng.random((20, 20)) < 0.1
    walls[[0, -1], :] = walls[:, [0, -1]] = True
    for _ in range(20):
        prey, predators = rng.integers(1, 19, size=(30, 2)), rng.integers(1, 18, size=(5, 2))
        np.testing.assert_array_equal(
            evader_actions(prey, predators, walls), reference_evader(prey, predators, walls)
        )


def nearest_body_distances(env: PursuitEnv) -> np.ndarray:
    prey, corners = env.prey_cells()[:, None, :], env.predator_cells()[None, :, :]
    gaps = np.maximum(np.maximum(corners - prey, prey - corners - 1), 0)
    return np.sqrt((gaps**2).sum(axis=-1)).min(axis=1)


def test_evading_prey_get_away_from_still_predators_and_are_tagged_less():
    tags = {}
    for controller in ("evader", "random"):
        env = pursuit_v0.parallel_env(map_size=24, max_cycles=60, prey_controller=controller)
        env.reset_arrays(seed=4)
        start = nearest_body_distances(env)
        for _ in range(10):
            env.step_arrays(np.full(env.n_agents, STAY["predator"]))
        if controller == "evader":
            assert nearest_body_distances(env).mean() > start.mean() + 1
        rng = np.random.default_rng(0)
        for _ in range(50):
            *_, info = env.step_arrays(rng.integers(0, 13, env.n_agents))
        tags[controller] = info["episode_tags"]
    assert tags["evader"] < tags["random"]


def tiny_prey_model() -> SoftHGRN:
    vec_env = make_graph_vec_env(
        pursuit_v0.parallel_env,
        n_envs=1,
        seed=0,
        env_kwargs=dict(map_size=16, learners="prey", max_cycles=10),
    )
    return SoftHGRN(
        "GraphPolicy", vec_env, buffer_size=1000, seed=0, policy_kwargs=dict(hidden_dim=8, n_heads=2)
    )


class Recorder:
    """Passes predict() calls to a model and records their episode_start and state arguments."""

    def __init__(self, model):
        self.model, self.calls = model, []

    @property
    def observation_space(self):
        return self.model.observation_space

    @property
    def policy(self):
        return self.model.policy

    def predict(self, observation, state=None, episode_start=None, deterministic=False):
        self.calls.append((episode_start.copy(), state))
        assert observation["obs"].dtype == np.uint8 and observation["neighbors"].dtype == np.int32
        return self.model.predict(observation, state, episode_start, deterministic)


def test_model_controller_threads_state_and_is_reproducible(tmp_path):
    model = tiny_prey_model()  # trained 0 steps on the prey side (6 prey)
    recorder = Recorder(model)
    env = pursuit_v0.parallel_env(map_size=20, max_cycles=4, prey_controller=ModelController(recorder))
    assert model.policy.n_agents == 10
    episodes = []
    for _ in range(2):
        env.reset_arrays(seed=11)
        episodes.append([env.step_arrays(np.full(env.n_agents, 2))[0] for _ in range(4)] + [env.prey_cells()])
    for array_a, array_b in zip(*episodes, strict=True):
        np.testing.assert_array_equal(array_a, array_b)
    starts = [bool(start.all()) for start, _ in recorder.calls]
    assert starts == [True, False, False, False] * 2
    assert [state is None for _, state in recorder.calls] == [True, False, False, False] * 2
    assert recorder.calls[1][1][0].shape == (1, 10, model.policy.state_dim)

    model.save(tmp_path / "prey.zip")
    controller = ModelController(tmp_path / "prey")
    loaded = pursuit_v0.parallel_env(map_size=20, max_cycles=4, prey_controller=controller)
    assert isinstance(controller.model, SoftHGRN) and controller.model.policy.n_agents == 10
    loaded.reset_arrays(seed=0)
    loaded.step_arrays(np.zeros(loaded.n_agents, dtype=np.int64))

    with pytest.raises(ValueError, match="trained on that side"):
        pursuit_v0.parallel_env(map_size=16, learners="prey", predator_controller=ModelController(model))


def test_a_function_drives_the_prey_and_bad_actions_are_refused():
    calls = []

    def step_right(observations, env):
        calls.append((sorted(observations), {obs.shape for obs in observations.values()}, env))
        return dict.fromkeys(observations, 5)  # x + 1

    env = small_env(prey_controller=step_right)
    env.reset_arrays(seed=0)
    before = env.prey_cells().copy()
    env.step_arrays(np.full(env.n_agents, STAY["predator"]))
    assert calls == [(sorted(f"prey_{i}" for i in range(6)), {(405,)}, env)]
    assert (
        set(map(tuple, env.prey_cells() - before)) <= {(0, 0), (1, 0)} and (env.prey_cells() != before).any()
    )
    with pytest.raises(ValueError, match=r"prey_controller must give 6 integer actions in 0..8"):
        env = small_env(prey_controller=lambda observations, env: dict.fromkeys(observations, 9))
        env.reset_arrays(seed=0)
        env.step_arrays(np.full(env.n_agents, STAY["predator"]))


def prey_cells_of_a_vec_env_episode(vec_env, n_steps: int = 4) -> np.ndarray:
    """Prey cells of copy 0 after each of ``n_steps`` vec-steps in which every predator stays."""
    vec_env.reset()
    cells = []
    for _ in range(n_steps):
        vec_env.step(np.full(vec_env.num_envs, STAY["predator"]))
        cells.append(vec_env.envs[0].prey_cells().copy())
    return np.array(cells)


def test_a_saved_model_path_is_loaded_by_make_graph_vec_env_not_by_the_env(tmp_path):
    tiny_prey_model().save(tmp_path / "prey.zip")
    path = str(tmp_path / "prey")
    with pytest.raises(
        ValueError, match="loads no saved model: pass it loaded .*ModelController.*make_graph_vec_env"
    ):
        pursuit_v0.parallel_env(map_size=20, prey_controller=path)

    env_kwargs = dict(map_size=20, max_cycles=10, prey_controller=path)
    vec_env = make_graph_vec_env(pursuit_v0.parallel_env, n_envs=2, env_kwargs=env_kwargs)
    controllers = [env.controller for env in vec_env.envs]
    assert isinstance(controllers[0], ModelController) and controllers[0] is controllers[1]
    assert isinstance(controllers[0].model, SoftHGRN) and controllers[0].model.policy.n_agents == 10
    episodes = []
    for _ in range(2):
        vec_env.seed(5)
        episodes.append(prey_cells_of_a_vec_env_episode(vec_env))
    np.testing.assert_array_equal(*episodes)


def test_make_graph_vec_env_names_a_controller_argument_without_a_saved_model(tmp_path):
    missing = r"prey_controller='chaser': No saved model at chaser \(nor chaser.zip\)"
    with pytest.raises(ValueError, match=missing):
        make_graph_vec_env("pursuit_v0", env_kwargs=dict(map_size=16, prey_controller="chaser"))


def test_prey_learners_get_minus_one_per_tag():
    env = small_env(learners="prey", map_size=20)
    assert env.n_agents == 10 and env.controller == "random"
    env.reset_arrays(seed=0)
    rng = np.random.default_rng(0)
    total = 0.0
    for _ in range(40):
        _, rewards, _, _, info = env.step_arrays(rng.integers(0, 9, env.n_agents))
        assert rewards.max() <= 0 and rewards.shape == (10,)
        assert -rewards.sum() == info["tags"]
        total += rewards.sum()
    assert total < 0


def test_prey_actions_move_as_documented():
    env = small_env(learners="prey", map_size=20, predator_controller=None)
    env.reset_arrays(seed=1)
    for action in itertools.chain(range(9), range(9)):
        before = env.prey_cells().copy()
        env.step_arrays(np.full(env.n_agents, action))
        moved = env.prey_cells() - before
        assert set(map(tuple, moved)) <= {(0, 0), PREY_MOVES[action]}


@pytest.mark.parametrize(
    "kwargs",
    [
        dict(map_size=8),
        dict(max_cycles=0),
        dict(learners="wolf"),
        dict(comm_range=-1),
        dict(max_neighbors=0),
        dict(render_mode="ansi"),
        dict(prey_controller="chaser"),
        dict(predator_controller="random"),
        dict(learners="prey", prey_controller="random"),
        dict(learners="prey", predator_controller="evader"),
    ],
)
def test_invalid_arguments_raise(kwargs):
    with pytest.raises(ValueError):
        pursuit_v0.parallel_env(**{"map_size": 16, **kwargs})


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(map_size="16"), r"map_size must be an integer >= 9 \(one predator\), got '16'"),
        (dict(map_size=16.0), r"map_size must be an integer >= 9 \(one predator\), got 16.0"),
        (dict(map_size=8), r"map_size must be an integer >= 9 \(one predator\), got 8"),
        (dict(max_cycles="5"), "max_cycles must be an integer >= 1, got '5'"),
        (dict(tag_penalty="x"), "tag_penalty must be a number, got 'x'"),
        (dict(tag_penalty=float("nan")), "tag_penalty must be a number, got nan"),
        (dict(comm_range="6"), "comm_range must be a number >= 0, got '6'"),
        (dict(max_neighbors=2.5), "max_neighbors must be an integer >= 1, got 2.5"),
        (dict(controller_deterministic="no"), "controller_deterministic must be true or false, got 'no'"),
    ],
)
def test_a_wrongly_typed_or_out_of_range_argument_names_it_and_its_range(kwargs, message):
    with pytest.raises(ValueError, match=message):
        pursuit_v0.parallel_env(**{"map_size": 16, **kwargs})


def test_invalid_controller_type_and_actions_raise():
    with pytest.raises(TypeError):
        small_env(prey_controller=3)
    env = small_env()
    env.reset_arrays(seed=0)
    for actions in ([0, 1], [0, 1, 13], [0, -1, 2]):
        with pytest.raises(ValueError):
            env.step_arrays(np.array(actions))


def test_render_rgb_array(monkeypatch):
    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")
    env = small_env(render_mode="rgb_array")
    env.reset_arrays(seed=0)
    frame = env.render()
    assert frame.ndim == 3 and frame.shape[2] == 3 and frame.dtype == np.uint8 and frame.max() > 0
    env.step_arrays(np.zeros(env.n_agents, dtype=np.int64))
    assert env.render().shape == frame.shape
    env.close()
    without_mode = small_env()
    without_mode.reset_arrays(seed=0)
    with pytest.warns(UserWarning):
        assert without_mode.render() is None


def test_render_human_with_dummy_display(monkeypatch):
    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")
    env = small_env(render_mode="human")
    env.reset_arrays(seed=0)
    assert env.render() is None
    env.close()
