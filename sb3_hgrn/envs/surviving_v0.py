"""Surviving: many agents forage food that regrows around moving resource points (from DGN).

PettingZoo-style module: ``surviving_v0.parallel_env(n_agents=100)`` builds a :class:`SurvivingEnv`.
"""

from __future__ import annotations

import math
from typing import Any

import gymnasium as gym
import numpy as np

from sb3_hgrn.envs.base import GraphParallelEnv, binary_table, check_agent_count
from sb3_hgrn.envs.graph import grid_neighbors
from sb3_hgrn.validation import check_flag, check_integer, check_number

N_ACTIONS = 5
EAT = 4
WALL = -1
MAX_FOOD_PER_CELL = 5
MAX_STORE = 10
FOOD_VALUE = 2
SURVIVE_REWARD = 0.4
STARVE_REWARD = -0.2
RESERVE_RANGE = (100, 120)  # inclusive
DROP_RANGE = (1, 5)  # inclusive
DROP_OFFSET = 3
WINDOW = 3
CELL_PIXELS = 8
MAX_ID_BITS = 32

_WALL_RGB = (128, 128, 128)
_AGENT_RGB = (220, 30, 30)
_RESOURCE_RGB = (40, 90, 230)


class SurvivingEnv(GraphParallelEnv):
    """Surviving: ``n_agents`` agents on a ``map_size x map_size`` grid must keep their food store up.

    Coordinates: cell ``(x, y)`` is row ``x`` (axis 0, drawn top to bottom) and column ``y`` (axis 1,
    left to right) of the map, walls included, so interior cells are ``1 <= x, y <= map_size - 2``.

    Rules, per step: actions are 0: ``x - 1``, 1: ``x + 1``, 2: ``y - 1``, 3: ``y + 1`` (a move into the
    wall does nothing), 4: eat (``store += 2 * food`` of the own cell, which is emptied; agents act in
    index order, so of several agents eating on one cell the lowest index gets the food). Then every
    store becomes ``clip(store - 1, 0, 10)`` and each agent gets +0.4 if its store is positive, else
    -0.2. Then, if the total food on the map is at most ``2 * n_agents + 4``, each resource point draws
    an amount in {1..5} and an offset ``(dx, dy)`` in [-3, 3]^2; if that cell is interior it gains the
    amount (capped at 5 per cell) and the point's reserve loses the amount; a point whose reserve is
    used up moves to a random interior cell with a fresh reserve in {100..120}. Stores start at 10, the
    map starts empty (unless ``food_map`` is given). Episodes end by truncation after ``max_cycles``.

    Observation: int8 vector of ``2 * ceil(log2(map_size)) + 9 + 9 + id_bits + 1`` entries (39 for the
    defaults), binary numbers most significant bit first:

    ======================  ==========================  ==============================================
    slice (defaults)        content                     values
    ======================  ==========================  ==============================================
    ``[0:5]``               own ``x`` in binary         0/1
    ``[5:10]``              own ``y`` in binary         0/1
    ``[10:19]``             3 x 3 map window            -1 wall, else food count 0..5
    ``[19:28]``             3 x 3 agent occupancy       1 if any agent stands there (own cell is 1)
    ``[28:38]``             agent index in binary       0/1, fixed width ``id_bits``
    ``[38]``                own food store              0..10
    ======================  ==========================  ==============================================

    Windows are flattened row-major over ``(dx, dy)`` in ``(-1, 0, 1)^2``, ``dx`` slowest. The width
    of the index does not depend on ``n_agents``, so a policy transfers between agent counts. With
    ``observe_position=False`` the own-position bits are all 0 (the layout stays the same): agents
    then know only what they see around them, their store and their index.

    Graph: agents within Chebyshev distance ``comm_range`` (self first, nearest first, ties by lower
    index, at most ``max_neighbors``), see :func:`sb3_hgrn.envs.graph.grid_neighbors`.

    A hand-made map (case study) is built from ``agent_positions`` ``(n_agents, 2)``, ``food_map``
    ``(map_size - 2, map_size - 2)`` (entry ``[i, j]`` is the food on cell ``(i + 1, j + 1)``) and
    ``resource_positions`` ``(n_resources, 2)``; each one given replaces the random placement at every
    reset.
    """

    metadata: dict[str, Any] = {
        "render_modes": ["rgb_array", "human"],
        "name": "surviving_v0",
        "render_fps": 10,
    }

    def __init__(
        self,
        n_agents: int = 100,
        map_size: int = 32,
        max_cycles: int = 500,
        n_resources: int = 8,
        comm_range: int = 3,
        max_neighbors: int = 16,
        id_bits: int = 10,
        observe_position: bool = True,
        render_mode: str | None = None,
        agent_positions: np.ndarray | None = None,
        food_map: np.ndarray | None = None,
        resource_positions: np.ndarray | None = None,
    ) -> None:
        _check_arguments(
            n_agents, map_size, max_cycles, n_resources, comm_range, max_neighbors, id_bits, observe_position
        )
        render_modes = self.metadata["render_modes"]
        if render_mode is not None and render_mode not in render_modes:
            raise ValueError(f"render_mode must be None or one of {render_modes}, got {render_mode!r}.")
        self.map_size = map_size
        self.max_cycles = max_cycles
        self.n_resources = n_resources
        self.comm_range = comm_range
        self.max_neighbors = max_neighbors
        self.id_bits = id_bits
        self.observe_position = observe_position
        self.render_mode = render_mode
        self.regrowth_threshold = 2 * n_agents + 4
        self.possible_agents = [f"agent_{i}" for i in range(n_agents)]
        self.agents: list[str] = []
        self._given_agent_cells = _given_cells(agent_positions, n_agents, map_size, "agent_positions")
        self._given_resource_cells = _given_cells(
            resource_positions, n_resources, map_size, "resource_positions"
        )
        self._given_food = _given_food_map(food_map, map_size)

        self._build_tables()
        self.shared_observation_space = self._observation_box()
        self.shared_action_space = gym.spaces.Discrete(N_ACTIONS)

        self._rng: np.random.Generator | None = None
        self._agent_cells = np.zeros(n_agents, dtype=np.int64)
        self._stores = np.zeros(n_agents, dtype=np.int64)
        self._claims = np.full(map_size * map_size, n_agents, dtype=np.int64)
        self._drops = np.zeros(map_size * map_size, dtype=np.int64)
        self._resource_cells = np.zeros((n_resources, 2), dtype=np.int64)
        self._reserves = np.zeros(n_resources, dtype=np.int64)
        self._food_total = 0
        self._steps = 0
        self._episode_running = False

    # --- construction helpers -------------------------------------------------------------------
    def _build_tables(self) -> None:
        """Precompute the cell layers, lookup tables and the observation layout.

        Cells are addressed by flat index ``x * map_size + y``. ``self._layers``
        ``(2 + 2 * coordinate_bits, map_size**2)`` int8 holds per cell: the food map (-1 on walls), the
        agent occupancy, then the bits of ``x`` and of ``y``, so the first observation entries of all
        agents are one gather from it.
        """
        size, n_cells = self.map_size, self.map_size * self.map_size
        coordinate_bits = math.ceil(math.log2(size))
        interior = np.zeros((size, size), dtype=bool)
        interior[1:-1, 1:-1] = True
        self._wall_map = np.where(interior, 0, WALL).astype(np.int8).ravel()
        self._n_wall_cells = int((~interior).sum())

        rows, columns = np.divmod(np.arange(n_cells), size)
        self._coordinates_of_cell = np.stack([rows, columns], axis=1)
        binary = binary_table(size, coordinate_bits)
        self._layers = np.zeros((2 + 2 * coordinate_bits, n_cells), dtype=np.int8)
        self._layers[2:] = np.concatenate([binary[rows], binary[columns]], axis=1).T
        self._bind_views()

        window_steps = np.arange(-(WINDOW // 2), WINDOW // 2 + 1)
        window = (window_steps[:, None] * size + window_steps[None, :]).ravel()
        position_layers = np.arange(2, 2 + 2 * coordinate_bits) * n_cells
        self._layer_offsets = np.concatenate([position_layers, window, n_cells + window])
        self._map_window_slice = slice(2 * coordinate_bits, 2 * coordinate_bits + window.size)
        self.obs_dim = self._layer_offsets.size + self.id_bits + 1
        self._observation_template = np.zeros((self.n_agents, self.obs_dim), dtype=np.int8)
        self._observation_template[:, self._layer_offsets.size : -1] = binary_table(
            self.n_agents, self.id_bits
        )

        moves = np.array([-size, size, -1, 1, 0])
        targets = np.arange(n_cells)[:, None] + moves[None, :]
        stays = ~interior.ravel()[np.clip(targets, 0, n_cells - 1)]
        self._next_cell = np.where(stays, np.arange(n_cells)[:, None], targets).ravel()

        raw_stores = np.arange(MAX_STORE + FOOD_VALUE * MAX_FOOD_PER_CELL + 1)
        self._store_after_step = np.clip(raw_stores - 1, 0, MAX_STORE)
        self._reward_of_store = np.where(raw_stores > 0, SURVIVE_REWARD, STARVE_REWARD).astype(np.float32)

        padded = np.full((size + 2 * DROP_OFFSET, size + 2 * DROP_OFFSET), -1, dtype=np.int64)
        padded[DROP_OFFSET:-DROP_OFFSET, DROP_OFFSET:-DROP_OFFSET] = np.where(
            interior, np.arange(n_cells).reshape(size, size), -1
        )
        self._interior_cell_of_padded = padded  # flat interior cell at (x + 3, y + 3), else -1
        # Every (dx, dy, amount) a resource point can draw, with dx, dy stored as dx + 3, dy + 3.
        drop_span = 2 * DROP_OFFSET + 1
        n_amounts = DROP_RANGE[1] - DROP_RANGE[0] + 1
        drop_dx, drop_dy, drop_amount = np.unravel_index(
            np.arange(drop_span * drop_span * n_amounts), (drop_span, drop_span, n_amounts)
        )
        self._padded_drop_offsets = np.stack([drop_dx, drop_dy], axis=1)
        self._drop_amounts = drop_amount + DROP_RANGE[0]

    def _observation_box(self) -> gym.spaces.Box:
        """Bounds of each observation entry, in the layout of the class docstring."""
        low = np.zeros(self.obs_dim, dtype=np.int8)
        high = np.ones(self.obs_dim, dtype=np.int8)
        low[self._map_window_slice] = WALL
        high[self._map_window_slice] = MAX_FOOD_PER_CELL
        high[-1] = MAX_STORE
        return gym.spaces.Box(low=low, high=high, dtype=np.int8)

    def _bind_views(self) -> None:
        """``_food`` and ``_occupancy``: the first two rows of ``_layers`` ``(n_cells,)``."""
        self._food = self._layers[0]
        self._occupancy = self._layers[1]

    # --- array API ------------------------------------------------------------------------------
    def reset_arrays(self, seed: int | None = None, options: dict | None = None) -> np.ndarray:
        """Start an episode. Returns observations ``(n_agents, obs_dim)`` int8.

        ``seed`` reseeds the generator; without it the first reset seeds from entropy and later
        resets continue the generator.
        """
        if seed is not None or self._rng is None:
            self._rng = np.random.default_rng(seed)
        self._food[:] = self._wall_map
        if self._given_food is not None:
            self._food.reshape(self.map_size, self.map_size)[1:-1, 1:-1] = self._given_food
        self._food_total = self._count_food()
        self._agent_cells = self._flat(self._given_or_random_cells(self._given_agent_cells, self.n_agents))
        self._resource_cells = self._given_or_random_cells(self._given_resource_cells, self.n_resources)
        self._reserves = self._rng.integers(RESERVE_RANGE[0], RESERVE_RANGE[1] + 1, size=self.n_resources)
        self._stores = np.full(self.n_agents, MAX_STORE, dtype=np.int64)
        self._steps = 0
        self._episode_running = True
        self._neighbor_cache = None
        return self._observe()

    def step_arrays(
        self, actions: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """Advance one step with ``actions`` ``(n_agents,)`` in ``0..4``.

        Returns ``(observations (n_agents, obs_dim) int8, rewards (n_agents,) float32,
        terminated (n_agents,) bool, truncated (n_agents,) bool, team_info)`` with
        ``team_info = {"food_on_map": int, "mean_store": float}`` measured after the step.
        """
        if not self._episode_running:
            raise RuntimeError("step_arrays() called outside an episode; call reset_arrays() first.")
        actions = np.asarray(actions)
        if actions.shape != (self.n_agents,) or actions.min() < 0 or actions.max() >= N_ACTIONS:
            raise ValueError(
                f"actions must be an integer array of shape ({self.n_agents},) with values 0..4."
            )
        self._agent_cells = self._next_cell[self._agent_cells * N_ACTIONS + actions]
        self._eat(np.flatnonzero(actions == EAT))
        self._stores = self._store_after_step[self._stores]
        rewards = self._reward_of_store[self._stores]
        if self.n_resources and self._food_total <= self.regrowth_threshold:
            self._regrow()
        self._steps += 1
        self._neighbor_cache = None
        truncated = self._steps >= self.max_cycles
        self._episode_running = not truncated
        team_info = {"food_on_map": self._food_total, "mean_store": int(self._stores.sum()) / self.n_agents}
        return (
            self._observe(),
            rewards,
            np.zeros(self.n_agents, dtype=bool),
            np.full(self.n_agents, truncated),
            team_info,
        )

    def _neighbor_lists(self) -> np.ndarray:
        """Agents within Chebyshev distance ``comm_range``: ``(n_agents, max_neighbors)`` int64.

        Row ``i`` is ``i`` itself, then its neighbours nearest first (ties by lower index); ``-1`` pads.
        """
        return grid_neighbors(self.agent_cells(), self.comm_range, self.max_neighbors)

    # --- state read-out (analysis, case studies) ------------------------------------------------
    def food_grid(self) -> np.ndarray:
        """Copy of the map ``(map_size, map_size)`` int8: food per cell, ``-1`` on walls."""
        return self._food.reshape(self.map_size, self.map_size).copy()

    def agent_cells(self) -> np.ndarray:
        """Agent cells ``(n_agents, 2)`` int64 as ``(x, y)``."""
        return self._coordinates_of_cell[self._agent_cells]

    def resource_cells(self) -> np.ndarray:
        """Resource point cells ``(n_resources, 2)`` int64 as ``(x, y)``."""
        return self._resource_cells.copy()

    def resource_reserves(self) -> np.ndarray:
        """Food left at each resource point, ``(n_resources,)`` int64."""
        return self._reserves.copy()

    # --- dynamics -------------------------------------------------------------------------------
    def _eat(self, eaters: np.ndarray) -> None:
        """Agents ``eaters`` ``(n_eaters,)`` (ascending) eat; the lowest index on each cell gets its food."""
        cells = self._agent_cells[eaters]
        food = self._food[cells]
        np.minimum.at(self._claims, cells, eaters)
        food *= self._claims[cells] == eaters
        self._claims[cells] = self.n_agents
        self._food[cells] = 0
        self._stores[eaters] += FOOD_VALUE * food
        self._food_total -= int(food.sum())

    def _regrow(self) -> None:
        """Every resource point drops food near itself; exhausted points move (see class docstring)."""
        draws = self._rng.integers(0, self._drop_amounts.size, size=self.n_resources)
        targets = self._resource_cells + self._padded_drop_offsets[draws]
        target_cells = self._interior_cell_of_padded[targets[:, 0], targets[:, 1]]
        inside = target_cells >= 0
        target_cells, amounts = target_cells[inside], self._drop_amounts[draws[inside]]
        np.add.at(self._drops, target_cells, amounts)
        self._food[target_cells] = np.minimum(
            self._food[target_cells] + self._drops[target_cells], MAX_FOOD_PER_CELL
        )
        self._drops[target_cells] = 0
        self._food_total = self._count_food()
        self._reserves[inside] -= amounts
        if self._reserves.min() <= 0:
            exhausted = np.flatnonzero(self._reserves <= 0)
            self._resource_cells[exhausted] = self._random_interior_cells(exhausted.size)
            self._reserves[exhausted] = self._rng.integers(
                RESERVE_RANGE[0], RESERVE_RANGE[1] + 1, size=exhausted.size
            )

    def _count_food(self) -> int:
        """Total food on the map (the food layer holds ``-1`` on each wall cell)."""
        return int(self._food.sum(dtype=np.int64)) + self._n_wall_cells

    # --- observation ----------------------------------------------------------------------------
    def _observe(self) -> np.ndarray:
        """Observations ``(n_agents, obs_dim)`` int8 in the layout of the class docstring."""
        self._occupancy[:] = 0
        self._occupancy[self._agent_cells] = 1
        observations = self._observation_template.copy()
        gathered = self._layers.reshape(-1)[self._agent_cells[:, None] + self._layer_offsets[None, :]]
        observations[:, : self._layer_offsets.size] = gathered
        observations[:, -1] = self._stores
        if not self.observe_position:
            observations[:, : self._map_window_slice.start] = 0
        return observations

    # --- placement helpers ----------------------------------------------------------------------
    def _flat(self, cells: np.ndarray) -> np.ndarray:
        """Flat map indices ``(n,)`` of cells ``(n, 2)``."""
        return cells[:, 0] * self.map_size + cells[:, 1]

    def _random_interior_cells(self, count: int) -> np.ndarray:
        """``(count, 2)`` uniformly random interior cells."""
        return self._rng.integers(1, self.map_size - 1, size=(count, 2))

    def _given_or_random_cells(self, given: np.ndarray | None, count: int) -> np.ndarray:
        """A copy of the ``given`` cells ``(count, 2)``, or random interior ones."""
        return given.copy() if given is not None else self._random_interior_cells(count)

    # --- rendering ------------------------------------------------------------------------------
    def _draw(self) -> np.ndarray:
        """The current state as an image.

        The image is ``(8 * map_size, 8 * map_size, 3)`` uint8: walls grey, food in shades of green,
        resource points blue, agents red; ``x`` runs downwards.
        """
        food_levels = np.arange(MAX_FOOD_PER_CELL + 1)
        food_colors = np.stack(
            [255 - 45 * food_levels, 255 - 25 * food_levels, 255 - 45 * food_levels], axis=1
        )
        palette = np.vstack([food_colors, _WALL_RGB]).astype(np.uint8)
        cell_colors = palette[np.where(self._food == WALL, len(palette) - 1, self._food)]
        cell_colors = cell_colors.reshape(self.map_size, self.map_size, 3)
        image = np.repeat(np.repeat(cell_colors, CELL_PIXELS, axis=0), CELL_PIXELS, axis=1)

        inner = np.zeros((CELL_PIXELS, CELL_PIXELS), dtype=bool)
        inner[2:-2, 2:-2] = True
        for flat_cells, color in (
            (self._flat(self._resource_cells), _RESOURCE_RGB),
            (self._agent_cells, _AGENT_RGB),
        ):
            marked = np.zeros(self._food.size, dtype=bool)
            marked[flat_cells] = True
            image[np.kron(marked.reshape(self.map_size, self.map_size), inner).astype(bool)] = color
        return image


# --- argument checks ----------------------------------------------------------------------------
def _check_arguments(
    n_agents: int,
    map_size: int,
    max_cycles: int,
    n_resources: int,
    comm_range: int,
    max_neighbors: int,
    id_bits: int,
    observe_position: bool,
) -> None:
    """Raise ``ValueError`` naming the argument, its valid range and its value for constructor arguments
    of a wrong type or outside their valid ranges."""
    check_integer("id_bits", id_bits, 1, MAX_ID_BITS)
    check_agent_count("n_agents", n_agents, 2**id_bits, f"2**id_bits, the agent index is {id_bits} bits wide")
    check_integer("map_size", map_size, 4, why="a wall ring around at least 2 x 2 cells")
    check_integer("max_cycles", max_cycles, 1)
    check_integer("n_resources", n_resources, 0)
    check_number("comm_range", comm_range, 0)
    check_integer("max_neighbors", max_neighbors, 1)
    check_flag("observe_position", observe_position)


def _given_cells(cells: np.ndarray | None, count: int, map_size: int, name: str) -> np.ndarray | None:
    """Validated copy ``(count, 2)`` int64 of user-given interior cells, or None."""
    if cells is None:
        return None
    array = np.asarray(cells)
    if array.shape != (count, 2) or not np.issubdtype(array.dtype, np.integer):
        raise ValueError(
            f"{name} must be an integer array of shape ({count}, 2), got {array.dtype} {array.shape}."
        )
    if array.size and (array.min() < 1 or array.max() > map_size - 2):
        raise ValueError(f"{name} must be interior cells, each coordinate in 1..{map_size - 2}.")
    return array.astype(np.int64)


def _given_food_map(food_map: np.ndarray | None, map_size: int) -> np.ndarray | None:
    """Validated copy ``(map_size - 2, map_size - 2)`` int8 of a user-given interior food map, or None."""
    if food_map is None:
        return None
    array = np.asarray(food_map)
    interior = map_size - 2
    if array.shape != (interior, interior) or not np.issubdtype(array.dtype, np.integer):
        raise ValueError(
            f"food_map must be an integer array of shape ({interior}, {interior}), "
            f"got {array.dtype} {array.shape}."
        )
    if array.min() < 0 or array.max() > MAX_FOOD_PER_CELL:
        raise ValueError(f"food_map values must lie in 0..{MAX_FOOD_PER_CELL}.")
    return array.astype(np.int8)


def parallel_env(**kwargs: Any) -> SurvivingEnv:
    """Build a :class:`SurvivingEnv` (PettingZoo-style module entry point)."""
    return SurvivingEnv(**kwargs)
