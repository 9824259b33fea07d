"""Pursuit: predators tag prey on MAgent2's ``adversarial_pursuit_v4`` map; one side learns.

PettingZoo-style module: ``pursuit_v0.parallel_env(learners="predator")`` builds a :class:`PursuitEnv`.
Needs MAgent2 (``pip install magent2==0.3.4``).
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np

from sb3_hgrn.envs.base import GraphParallelEnv
from sb3_hgrn.envs.driven_sides import Controller, DrivenSide, controller_paths, make_controller
from sb3_hgrn.envs.graph import grid_neighbors
from sb3_hgrn.validation import check_flag, check_integer, check_number

SIDES = ("predator", "prey")
SCRIPTED_CONTROLLERS = {"predator": ("random",), "prey": ("random", "evader")}
DEFAULT_CONTROLLERS = {"predator": "random", "prey": "evader"}
FIRST_TAG_ACTION = 5  # predator actions 5..12 tag one of the 8 cells touching the body
PREDATOR_BODY = 2  # predators occupy 2 x 2 cells, prey 1 cell
# Prey action a moves by (dx, dy) = (a % 3 - 1, a // 3 - 1); 4 stays (MAgent's move range, row-major).
PREY_MOVES = np.array([(dx, dy) for dy in (-1, 0, 1) for dx in (-1, 0, 1)], dtype=np.int32)
MIN_MAP_SIZE = 9  # the smallest map with a predator: int(9 * 9 * 0.0125) = 1
SEED_HIGH = 2**31 - 1  # MAgent takes a C int seed


class PursuitEnv(GraphParallelEnv):
    """Pursuit (MAgent2 ``adversarial_pursuit_v4``): one side learns, a controller drives the other.

    Map: ``map_size x map_size`` cells with a wall border and 3 % random walls; MAgent places
    ``int(map_size**2 * 0.0125)`` predators (2 x 2 bodies) and ``int(map_size**2 * 0.025)`` prey
    (1 cell) at random: 25 and 50 on the paper's 45 x 45 map. ``map_size >= 9`` (one predator);
    a graph VecEnv needs two learners: ``map_size >= 13`` for predators, ``>= 9`` for prey.

    Coordinates: a cell is ``(x, y)`` as MAgent's ``get_pos`` gives it, ``x`` the column and ``y`` the
    row of the rendered map and of the observation windows. A predator's cell is the top-left
    (smallest ``x`` and ``y``) cell of its body, which covers ``x..x+1, y..y+1``; all bodies have the
    same shape, so distances between these cells equal distances between body centres.

    Actions: predators ``Discrete(13)``: 0 ``y - 1``, 1 ``x - 1``, 2 stay, 3 ``x + 1``, 4 ``y + 1``,
    5..12 tag one of the 8 cells touching the sides of the body: ``(x, y-1)``, ``(x+1, y-1)``,
    ``(x-1, y)``, ``(x+2, y)``, ``(x-1, y+1)``, ``(x+2, y+1)``, ``(x, y+2)``, ``(x+1, y+2)``; prey
    ``Discrete(9)``: action ``a`` moves by ``(a % 3 - 1, a // 3 - 1)`` (4 stays). A move into a wall
    or an occupied cell fails.

    Rewards (MAgent's): a predator gets ``+1`` per prey it tags plus ``tag_penalty`` (default -0.2)
    per tag action, hit or miss; a prey gets ``-1`` each time it is tagged. Tags do no damage, so
    nobody dies and episodes end only by truncation after ``max_cycles`` steps.

    Observation of a learner: its MAgent view (predators 10 x 10, prey 9 x 9 cells around the body,
    channels walls, own team, own team hp, other team, other team hp), flattened in
    ``(row, column, channel)`` order to a uint8 vector of 500 (predators) or 405 (prey) zeros and ones.

    Graph: learners within Euclidean distance ``comm_range`` of each other (self first, nearest
    first, ties by lower index, at most ``max_neighbors``), see
    :func:`sb3_hgrn.envs.graph.grid_neighbors`.

    Controllers of the other side, built by :func:`sb3_hgrn.envs.driven_sides.make_controller` (as
    for :class:`~sb3_hgrn.envs.wrappers.DrivenAgents`): ``"random"`` (uniform actions), for prey
    ``"evader"`` (:func:`evader_actions`), a function ``(observations, env) -> actions`` (the
    controlled agents ``prey_0``, ... or ``predator_0``, ... by name, and this env), or a model: any
    object with SB3's ``predict(observation, state=..., episode_start=..., deterministic=...)``,
    called with ``{"obs": (n, obs_dim) uint8, "neighbors": (n, K) int32}`` for the ``n`` controlled
    agents and returning ``(actions (n,), state)``. The graph is the controlled side's own
    (``comm_range``), ``K`` wide: the width of ``observation_space["neighbors"]`` where the model has
    a Dict observation space, else ``max_neighbors``. Its recurrent state is threaded through the
    episode and reset at episode starts; it acts with ``controller_deterministic``. Two methods are
    optional: ``bind(observation_space, n_agents)``, called once here with the controlled side's
    observation ``Box`` and agent count (to check that the model fits that side and size it to it),
    and ``seed(seed)``, called with an int from the env's generator before every ``predict``. The env
    loads no saved model: ``sb3_hgrn.common.saved_controllers.ModelController`` wraps a loaded sb3_hgrn
    model or a saved one's path and has both methods (its samples repeat with the env's seed), and
    :func:`sb3_hgrn.make_graph_vec_env` and the command line turn a path given in ``env_kwargs``
    into one (see :func:`model_paths`). :attr:`controller` is the controller as given (its name where
    it was left ``None``).

    Seeding: one numpy generator, reseeded by ``reset(seed=...)`` (first reset without a seed: from
    entropy; later unseeded resets continue it), seeds MAgent's engine at every reset (map, walls,
    placement, order of tags) and drives the random controller and the seeds handed to a model
    controller's ``seed``, so a seeded episode repeats exactly.

    MAgent2 is driven through its raw ``GridWorld`` (``set_action``/``step``/``get_reward``/
    ``get_observation``/``clear_dead`` on group arrays): 0.05 ms per step at map 45 against 0.3 ms
    through its dict API. The env never steps MAgent outside an episode (stepping after the end
    crashes MAgent2).

    :param map_size: side of the square map in cells (45 in the paper).
    :param max_cycles: steps per episode.
    :param learners: ``"predator"`` or ``"prey"``: the side whose agents are this env's agents.
    :param prey_controller: controller of the prey when predators learn (default ``"evader"``).
    :param predator_controller: controller of the predators when prey learn (default ``"random"``).
    :param controller_deterministic: greedy actions for model controllers.
    :param tag_penalty: predator reward per tag action.
    :param comm_range: communication range in cells (Euclidean).
    :param max_neighbors: width of the neighbour lists, self included.
    :param render_mode: ``None``, ``"rgb_array"`` (MAgent2's frame) or ``"human"`` (a pygame window).
    """

    metadata: dict[str, Any] = {
        "render_modes": ["rgb_array", "human"],
        "name": "pursuit_v0",
        "render_fps": 5,
    }

    def __init__(
        self,
        map_size: int = 45,
        max_cycles: int = 500,
        learners: str = "predator",
        prey_controller: Any = None,
        predator_controller: Any = None,
        controller_deterministic: bool = False,
        tag_penalty: float = -0.2,
        comm_range: float = 6.0,
        max_neighbors: int = 16,
        render_mode: str | None = None,
    ) -> None:
        _check_arguments(
            map_size, max_cycles, learners, controller_deterministic, tag_penalty, comm_range, max_neighbors
        )
        render_modes = self.metadata["render_modes"]
        if render_mode is not None and render_mode not in render_modes:
            raise ValueError(f"render_mode must be None or one of {render_modes}, got {render_mode!r}.")
        try:
            from magent2.environments import adversarial_pursuit_v4
        except ImportError as error:
            raise ImportError("pursuit_v0 needs MAgent2: pip install magent2==0.3.4") from error

        self.map_size = map_size
        self.max_cycles = max_cycles
        self.learners = learners
        self.tag_penalty = tag_penalty
        self.comm_range = comm_range
        self.max_neighbors = max_neighbors
        self.controller_deterministic = controller_deterministic
        self.render_mode = render_mode
        self._magent = adversarial_pursuit_v4.parallel_env(
            map_size=map_size, max_cycles=max_cycles, render_mode=render_mode, tag_penalty=tag_penalty
        )
        self._grid = self._magent.env  # MAgent's GridWorld
        predator_handle, prey_handle = self._magent.handles
        self.opponents = SIDES[1 - SIDES.index(learners)]
        self._handles = {"predator": predator_handle, "prey": prey_handle}
        self._sizes = {side: self._grid.get_num(handle) for side, handle in self._handles.items()}
        if min(self._sizes.values()) < 1:
            raise ValueError(f"map_size {map_size} gives {self._sizes}; use map_size >= {MIN_MAP_SIZE}.")
        self.possible_agents = [f"{learners}_{i}" for i in range(self._sizes[learners])]
        self.agents: list[str] = []
        self._obs_dims = {
            side: int(np.prod(self._grid.get_view_space(handle))) for side, handle in self._handles.items()
        }
        self._n_actions = {
            side: int(self._grid.get_action_space(handle)[0]) for side, handle in self._handles.items()
        }
        self.shared_observation_space = gym.spaces.Box(0, 1, (self._obs_dims[learners],), dtype=np.uint8)
        self.shared_action_space = gym.spaces.Discrete(self._n_actions[learners])

        controllers = {"predator": predator_controller, "prey": prey_controller}
        if controllers[learners] is not None:
            raise ValueError(f"{learners}_controller must be None when the {learners} side learns.")
        spec = controllers[self.opponents]
        self.controller = DEFAULT_CONTROLLERS[self.opponents] if spec is None else spec
        self._rng: np.random.Generator | None = None
        self._walls = np.zeros((map_size, map_size), dtype=bool)
        self._side = PursuitSide(self)
        self._driver = make_controller(
            self.controller,
            self._side,
            argument=f"{self.opponents}_controller",
            deterministic=controller_deterministic,
            scripted={"evader": EvaderController} if self.opponents == "prey" else None,
        )
        self._steps = 0
        self._episode_tags = 0
        self._episode_running = False
        self._cell_cache: dict[str, np.ndarray] = {}

    # --- array API ------------------------------------------------------------------------------
    def reset_arrays(self, seed: int | None = None, options: dict | None = None) -> np.ndarray:
        """Start an episode. Returns the learners' observations ``(n_agents, obs_dim)`` uint8.

        ``seed`` reseeds the generator; without it the first reset seeds from entropy and later
        resets continue the generator.
        """
        if seed is not None or self._rng is None:
            self._rng = np.random.default_rng(seed)
        self._grid.set_seed(int(self._rng.integers(SEED_HIGH)))
        self._grid.reset()
        self._magent.generate_map()
        sizes = {side: self._grid.get_num(handle) for side, handle in self._handles.items()}
        if sizes != self._sizes:
            raise RuntimeError(f"MAgent2 placed {sizes} agents instead of {self._sizes}.")
        walls = self._grid._get_walls_info()
        self._walls[:] = False
        self._walls[walls[:, 0], walls[:, 1]] = True
        self._driver.reset()
        self._steps = 0
        self._episode_tags = 0
        self._episode_running = True
        self._neighbor_cache = None
        self._cell_cache = {}
        return self._observe(self.learners)

    def step_arrays(
        self, actions: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """Advance one step with the learners' ``actions`` ``(n_agents,)``.

        Returns ``(observations (n_agents, obs_dim) uint8, rewards (n_agents,) float32,
        terminated (n_agents,) bool (never true), truncated (n_agents,) bool, team_info)`` with
        ``team_info = {"tags": int, "tag_attempts": int, "episode_tags": int}``: prey tagged this
        step (a prey tagged by two predators counts twice), tag actions of all predators this step
        (hits and misses), and tags since the episode started.
        """
        if not self._episode_running:
            raise RuntimeError(
                "step_arrays() called outside an episode (MAgent2 crashes when stepped after the end); "
                "call reset_arrays() first."
            )
        actions = np.asarray(actions)
        n_actions = self._n_actions[self.learners]
        if actions.shape != (self.n_agents,) or actions.min() < 0 or actions.max() >= n_actions:
            raise ValueError(
                f"actions must be an integer array of shape ({self.n_agents},) with values "
                f"0..{n_actions - 1}."
            )
        side_actions = {
            self.learners: actions.astype(np.int32),
            self.opponents: self._controller_actions(),
        }
        for side, handle in self._handles.items():
            self._grid.set_action(handle, side_actions[side])
        self._grid.step()
        rewards = self._grid.get_reward(self._handles[self.learners])
        prey_rewards = rewards if self.learners == "prey" else self._grid.get_reward(self._handles["prey"])
        observations = self._observe(self.learners)
        self._grid.clear_dead()

        tags = round(-float(prey_rewards.sum()))
        self._episode_tags += tags
        self._steps += 1
        self._neighbor_cache = None
        self._cell_cache = {}
        truncated = self._steps >= self.max_cycles
        self._episode_running = not truncated
        team_info = {
            "tags": tags,
            "tag_attempts": int(np.count_nonzero(side_actions["predator"] >= FIRST_TAG_ACTION)),
            "episode_tags": self._episode_tags,
        }
        return (
            observations,
            rewards,
            np.zeros(self.n_agents, dtype=bool),
            np.full(self.n_agents, truncated),
            team_info,
        )

    def _neighbor_lists(self) -> np.ndarray:
        """Learners within Euclidean distance ``comm_range``: ``(n_agents, max_neighbors)`` int64.

        Row ``i`` is ``i`` itself, then its neighbours nearest first (ties by lower index); ``-1`` pads.
        """
        return grid_neighbors(self.agent_cells(), self.comm_range, self.max_neighbors, "euclidean")

    # --- state read-out (analysis, tests) -------------------------------------------------------
    def predator_cells(self) -> np.ndarray:
        """Top-left cells of the predators' bodies ``(n_predators, 2)`` int64 as ``(x, y)``, read-only."""
        return self._cells("predator")

    def prey_cells(self) -> np.ndarray:
        """Prey cells ``(n_prey, 2)`` int64 as ``(x, y)``, read-only."""
        return self._cells("prey")

    def agent_cells(self) -> np.ndarray:
        """The learners' cells ``(n_agents, 2)`` int64 as ``(x, y)`` (the graph's positions), read-only."""
        return self._cells(self.learners)

    def _cells(self, side: str) -> np.ndarray:
        """Cells of one side, read from MAgent once per step."""
        cells = self._cell_cache.get(side)
        if cells is None:
            cells = self._grid.get_pos(self._handles[side]).astype(np.int64)
            cells.flags.writeable = False
            self._cell_cache[side] = cells
        return cells

    # --- the other side -------------------------------------------------------------------------
    def _observe(self, side: str) -> np.ndarray:
        """Observations of one side ``(n, obs_dim)`` uint8 (copied out of MAgent's buffer)."""
        views, _ = self._grid.get_observation(self._handles[side])
        return views.reshape(len(views), -1).astype(np.uint8)

    def _controller_actions(self) -> np.ndarray:
        """Actions ``(n_controlled,)`` int32 of the controlled side in the current state.

        :raises ValueError: when the controller gives other than one valid action per agent.
        """
        side = self.opponents
        actions = np.asarray(self._driver.actions(self._side))
        n, n_actions = self._sizes[side], self._n_actions[side]
        if (
            actions.shape != (n,)
            or actions.dtype.kind not in "iu"
            or actions.min() < 0
            or actions.max() >= n_actions
        ):
            raise ValueError(
                f"The {side}_controller must give {n} integer actions in 0..{n_actions - 1} (one per "
                f"{side}), got {actions.dtype} {actions.shape}."
            )
        return actions.astype(np.int32, copy=False)

    # --- rendering ------------------------------------------------------------------------------
    def render(self) -> np.ndarray | None:
        """MAgent2's picture of the map: ``"rgb_array"`` returns it (``(376, 360, 3)`` uint8 at map 45),
        ``"human"`` shows it in a pygame window (headless: set ``SDL_VIDEODRIVER=dummy``)."""
        if self.render_mode is None:
            gym.logger.warn("render() called without a render_mode; pass render_mode='rgb_array' or 'human'.")
            return None
        return self._magent.render()

    def close(self) -> None:
        """Close MAgent2's renderer if one was opened."""
        self._magent.close()


class PursuitSide(DrivenSide):
    """The side of a :class:`PursuitEnv` that its controller drives: all its agents, always alive,
    named ``prey_0``, ... or ``predator_0``, ..., with their graph of ``comm_range``."""

    def __init__(self, env: PursuitEnv) -> None:
        side = env.opponents
        self.env = env
        self.names = tuple(f"{side}_{i}" for i in range(env._sizes[side]))
        self.action_spaces = (gym.spaces.Discrete(env._n_actions[side]),) * len(self.names)
        self.observation_space = gym.spaces.Box(0, 1, (env._obs_dims[side],), dtype=np.uint8)
        self._side = side
        self._all = np.arange(len(self.names))

    @property
    def rng(self) -> np.random.Generator:
        return self.env._rng

    def living(self) -> np.ndarray:
        return self._all

    def observations(self) -> np.ndarray:
        """``(n, obs_dim)`` uint8."""
        return self.env._observe(self._side)

    def named_observations(self) -> dict[str, np.ndarray]:
        return dict(zip(self.names, self.observations(), strict=True))

    def neighbors(self, width: int | None) -> np.ndarray:
        env = self.env
        width = env.max_neighbors if width is None else width
        return grid_neighbors(env._cells(self._side), env.comm_range, width, "euclidean").astype(np.int32)


class EvaderController(Controller):
    """Pursuit's scripted prey (:func:`evader_actions`)."""

    def actions(self, side: PursuitSide) -> np.ndarray:
        env = side.env
        return evader_actions(env.prey_cells(), env.predator_cells(), env._walls)


def evader_actions(prey_cells: np.ndarray, predator_cells: np.ndarray, walls: np.ndarray) -> np.ndarray:
    """Scripted prey: every prey takes the move that gets it farthest from the nearest predator.

    Distances are Euclidean from a cell to the nearest cell of a predator's 2 x 2 body. Each prey
    picks its nearest predator (ties: lower index), then, among the 9 moves (staying included) whose
    target is not a wall, the one whose target lies farthest from that predator's body (ties: lower
    action). Cells held by other agents are not avoided: MAgent then leaves the prey in place.

    Args:
        prey_cells: ``(n_prey, 2)`` integer prey cells ``(x, y)``.
        predator_cells: ``(n_predators, 2)`` integer top-left cells of the predators' bodies.
        walls: ``(map_size, map_size)`` bool, ``walls[x, y]`` true on walls, including a border
            ring that every prey stands inside.

    Returns:
        ``(n_prey,)`` int64 prey actions in ``0..8`` (action ``a`` moves by ``(a % 3 - 1, a // 3 - 1)``).
    """
    # Doubled coordinates keep everything integer: a body's centre is 2 * corner + 1 and a cell's gap to
    # the body along an axis is (|2 * cell - centre| - 1) / 2; squared doubled gaps rank like distances.
    doubled_prey = 2 * np.asarray(prey_cells, dtype=np.int32)
    centres = 2 * np.asarray(predator_cells, dtype=np.int32) + PREDATOR_BODY - 1
    x, y = doubled_prey[:, 0:1], doubled_prey[:, 1:2]
    nearest = np.argmin(_doubled_squared_gaps(x, y, centres[:, 0], centres[:, 1]), axis=1)
    target_x, target_y = x + 2 * PREY_MOVES[:, 0], y + 2 * PREY_MOVES[:, 1]
    centre_x, centre_y = centres[nearest, 0:1], centres[nearest, 1:2]
    scores = _doubled_squared_gaps(target_x, target_y, centre_x, centre_y)  # (n_prey, 9)
    scores[walls[target_x >> 1, target_y >> 1]] = -1
    return np.argmax(scores, axis=1)


def _doubled_squared_gaps(
    x: np.ndarray, y: np.ndarray, centre_x: np.ndarray, centre_y: np.ndarray
) -> np.ndarray:
    """Squared doubled gaps ``(2 gap_x)**2 + (2 gap_y)**2`` of doubled cells to doubled body centres."""
    gap_x, gap_y = np.abs(x - centre_x) - 1, np.abs(y - centre_y) - 1
    return gap_x * gap_x + gap_y * gap_y


def model_paths(env_kwargs: dict[str, Any]) -> dict[str, str]:
    """The controllers of ``env_kwargs`` given as saved models' paths, by argument name.

    :func:`sb3_hgrn.make_graph_vec_env` loads these before it builds the env (the env itself takes
    only loaded models), without running code from the files (see ``sb3_hgrn.common.safe_load``).
    """
    return controller_paths(env_kwargs, {f"{side}_controller": SCRIPTED_CONTROLLERS[side] for side in SIDES})


def _check_arguments(
    map_size: int,
    max_cycles: int,
    learners: str,
    controller_deterministic: bool,
    tag_penalty: float,
    comm_range: float,
    max_neighbors: int,
) -> None:
    """Raise ``ValueError`` naming the argument, its valid range and its value for constructor arguments
    of a wrong type or outside their valid ranges (the map size sets the agent counts)."""
    check_integer("map_size", map_size, MIN_MAP_SIZE, why="one predator")
    check_integer("max_cycles", max_cycles, 1)
    if learners not in SIDES:
        raise ValueError(f"learners must be one of {SIDES}, got {learners!r}.")
    check_flag("controller_deterministic", controller_deterministic)
    check_number("tag_penalty", tag_penalty)
    check_number("comm_range", comm_range, 0)
    check_integer("max_neighbors", max_neighbors, 1)


def parallel_env(**kwargs: Any) -> PursuitEnv:
    """Build a :class:`PursuitEnv` (PettingZoo-style module entry point)."""
    return PursuitEnv(**kwargs)
