"""Cooperative Treasure Collection: hunters collect treasure and dump it at banks of its colour (from MAAC).

PettingZoo-style module: ``ctc_v0.parallel_env(n_hunters=20)`` builds a :class:`TreasureCollectionEnv`,
a heterogeneous env with three agent groups (hunters, red banks, blue banks).
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np

from sb3_hgrn.envs.base import (
    AgentGroup,
    GraphParallelEnv,
    binary_table,
    check_agent_count,
    padded_observation_space,
)
from sb3_hgrn.envs.graph import grid_neighbors
from sb3_hgrn.validation import check_integer, check_number

HUNTER, RED_BANK, BLUE_BANK = 0, 1, 2  # group ids
GROUP_NAMES = ("hunter", "red_bank", "blue_bank")
RED, BLUE = 0, 1  # colours
N_HUNTER_ACTIONS = 7
N_BANK_ACTIONS = 5
COLLECT, DUMP = 5, 6  # hunter actions; 0..3 move, 4 stays
WALL_WIDTH = 3
WALL = -1
WINDOW = 7
COORDINATE_BITS = 7
MAX_MAP_SIZE = 2**COORDINATE_BITS
MAX_CARRY = 5
MAX_TREASURE_PER_CELL = 5  # per colour
MAX_COUNT = int(np.iinfo(np.int8).max)
STEP_REWARD = -0.01
COLLECT_REWARD = 0.2
DELIVERY_REWARD = 1.0
RESERVE_RANGE = (100, 120)  # inclusive
DROP_RANGE = (1, 3)  # inclusive
DROP_OFFSET = 5
CELL_PIXELS = 8

# Map layers, one row of ``n_cells`` int8 each; the observations gather from them.
HUNTERS, RED_BANKS, BLUE_BANKS = 0, 1, 2  # agent counts (= group ids)
RED_RESOURCES, BLUE_RESOURCES = 3, 4  # resource point counts
RED_TREASURE, BLUE_TREASURE = 5, 6  # treasure on the ground, -1 on walls
RED_CARRIED, BLUE_CARRIED = 7, 8  # treasure carried by the hunters standing on the cell
ZERO = 9  # always 0: pads the bank observations to the hunter width
X_BITS = 10  # then 7 rows of x bits and 7 rows of y bits
N_LAYERS = X_BITS + 2 * COORDINATE_BITS
HUNTER_CHANNELS = (HUNTERS, RED_BANKS, BLUE_BANKS, RED_RESOURCES, BLUE_RESOURCES, RED_TREASURE, BLUE_TREASURE)
BANK_CHANNELS = {
    RED_BANK: (HUNTERS, RED_BANKS, RED_RESOURCES, RED_TREASURE, RED_CARRIED),
    BLUE_BANK: (HUNTERS, BLUE_BANKS, BLUE_RESOURCES, BLUE_TREASURE, BLUE_CARRIED),
}
HUNTER_GATHER = 2 * COORDINATE_BITS + len(HUNTER_CHANNELS) * WINDOW * WINDOW  # 357
HUNTER_OBS_DIM = HUNTER_GATHER + 2  # 359: + carried red, carried blue
BANK_OBS_DIM = 2 * COORDINATE_BITS + len(BANK_CHANNELS[RED_BANK]) * WINDOW * WINDOW  # 259

_WALL_RGB = (128, 128, 128)
_RESOURCE_RGB = ((170, 0, 0), (0, 0, 170))
_BANK_RGB = ((235, 60, 60), (60, 60, 235))
_HUNTER_RGB = (20, 150, 20)


def _window_slice(channel: int) -> slice:
    """Where window channel ``channel`` lies in an observation (after the position bits)."""
    start = 2 * COORDINATE_BITS + channel * WINDOW * WINDOW
    return slice(start, start + WINDOW * WINDOW)


class TreasureCollectionEnv(GraphParallelEnv):
    """Cooperative Treasure Collection on a ``map_size x map_size`` grid with a 3-cell wall ring.

    Coordinates: cell ``(x, y)`` is row ``x`` (axis 0, drawn top to bottom) and column ``y`` (axis 1)
    of the map, walls included, so interior cells are ``3 <= x, y <= map_size - 4`` ([3, 36]^2 by
    default). Agents, in this order: ``n_hunters`` hunters ``hunter_i`` (group 0), ``n_red_banks`` red
    banks ``red_bank_i`` (group 1), ``n_blue_banks`` blue banks ``blue_bank_i`` (group 2), all at random
    interior cells (or given ones) at reset; any number of agents and resource points may share a cell.

    Actions: 0: ``x - 1``, 1: ``x + 1``, 2: ``y - 1``, 3: ``y + 1`` (a move into the wall does nothing),
    4: stay; hunters also have 5: collect and 6: dump (both stay on the cell).

    Rules, per step (every agent gets -0.01 per step):

    1. Hunters act in index order. *Collect*: take the treasure lying on the own cell, red first, up to
       a carried total of 5 (red + blue), +0.2 per item taken; of several hunters collecting on one cell
       the lowest index takes first (red, then blue), the next one takes from what is left, and so on.
       *Dump*: for each colour carried, if at least one bank of that colour stands within the 3 x 3
       neighbourhood of the hunter (Chebyshev distance <= 1, own cell included), all carried items of
       that colour are delivered: the hunter gets +1 per item, and each of the ``k`` banks of that colour
       in the neighbourhood gets ``+items / k`` (an exact fraction, no rounding; a bank near several
       dumping hunters gets the sum of its shares). Items of a colour with no bank nearby stay carried.
    2. Then red banks and blue banks move.
    3. Treasure regrowth, per colour, after the hunters' actions: if the treasure of that colour on the
       map is below ``2 * n_hunters``, each resource point of that colour draws an amount in {1..3} and
       an offset ``(dx, dy)`` in [-5, 5]^2; if that cell is interior it gains the amount (capped at 5 per
       colour and cell) and the point's reserve loses the whole amount; a drop outside the interior is
       lost and costs nothing. A point whose reserve is used up moves to a random interior cell with a
       fresh reserve in {100..120}. The map starts without treasure (unless given) and hunters carry
       nothing. Episodes end by truncation after ``max_cycles``.

    Interpretations of the order: a hunter that collects or dumps does not move, and treasure taken by
    one hunter only matters to hunters on the same cell, so the index order only decides contested
    treasure; all hunter moves, then all bank moves, are applied at once (no move depends on another),
    and dumps see the banks where they stood before moving. Collecting with a full load, or dumping
    with no matching bank nearby, is allowed and does nothing.

    Observation: int8. Hunters have 359 entries, banks 259 (the array API pads them with zeros to
    359); binary numbers most significant bit first, windows ``7 x 7`` around the own cell flattened
    channel by channel, each row-major over ``(dx, dy)`` in ``[-3, 3]^2``, ``dx`` slowest:

    ===============  =========================================  ===========================================
    slice            hunter                                     bank of colour ``c`` (red or blue)
    ===============  =========================================  ===========================================
    ``[0:7]``        own ``x`` in binary (0/1)                  own ``x`` in binary
    ``[7:14]``       own ``y`` in binary (0/1)                  own ``y`` in binary
    ``[14:63]``      hunters per cell                           hunters per cell
    ``[63:112]``     red banks per cell                         banks of colour ``c`` per cell
    ``[112:161]``    blue banks per cell                        resource points of colour ``c`` per cell
    ``[161:210]``    red resource points per cell               treasure of colour ``c`` on the ground
    ``[210:259]``    blue resource points per cell              colour-``c`` treasure carried by the hunters
                                                                standing on the cell
    ``[259:308]``    red treasure on the ground                 (zero padding in the array API)
    ``[308:357]``    blue treasure on the ground                (zero padding)
    ``[357]``        carried red treasure 0..5                  (zero padding)
    ``[358]``        carried blue treasure 0..5                 (zero padding)
    ===============  =========================================  ===========================================

    Counts of agents, resource points and carried treasure are clipped to 127; the agent itself is
    counted at the window centre. Walls: every treasure-on-the-ground channel holds -1 on wall cells
    (treasure 0..5 elsewhere); all other channels are 0 there. The observation size does not depend
    on the agent counts (policies transfer); positions use 7 bits, so ``map_size <= 128``. The original
    encoded ``x`` twice and never ``y``; both are encoded here.

    Graph: all agents of all groups within Chebyshev distance ``comm_range`` (self first, nearest first,
    ties by lower index, at most ``max_neighbors``), see :func:`sb3_hgrn.envs.graph.grid_neighbors`.

    Rewards are float32. ``team_info`` after each step: ``collected`` (items picked up so far this
    episode), ``delivered_red`` and ``delivered_blue`` (items delivered so far this episode),
    ``treasure_on_map`` (items on the ground now) and ``carried`` (items carried by hunters now).

    A hand-made state (tests, case studies) is built from ``hunter_positions`` ``(n_hunters, 2)``,
    ``red_bank_positions`` / ``blue_bank_positions`` ``(n_*_banks, 2)``, ``red_resource_positions`` /
    ``blue_resource_positions`` ``(n_*_resources, 2)`` (interior cells ``(x, y)``) and ``red_treasure`` /
    ``blue_treasure`` ``(map_size - 6, map_size - 6)`` (entry ``[i, j]`` is the treasure on cell
    ``(i + 3, j + 3)``, 0..5); each one given replaces the random placement at every reset.
    """

    metadata: dict[str, Any] = {
        "render_modes": ["rgb_array", "human"],
        "name": "ctc_v0",
        "render_fps": 10,
    }

    def __init__(
        self,
        n_hunters: int = 20,
        n_red_banks: int = 10,
        n_blue_banks: int = 10,
        map_size: int = 40,
        max_cycles: int = 500,
        n_red_resources: int = 5,
        n_blue_resources: int = 5,
        comm_range: int = 5,
        max_neighbors: int = 24,
        render_mode: str | None = None,
        hunter_positions: np.ndarray | None = None,
        red_bank_positions: np.ndarray | None = None,
        blue_bank_positions: np.ndarray | None = None,
        red_resource_positions: np.ndarray | None = None,
        blue_resource_positions: np.ndarray | None = None,
        red_treasure: np.ndarray | None = None,
        blue_treasure: np.ndarray | None = None,
    ) -> None:
        _check_arguments(
            n_hunters,
            n_red_banks,
            n_blue_banks,
            map_size,
            max_cycles,
            n_red_resources,
            n_blue_resources,
            comm_range,
            max_neighbors,
        )
        render_modes = self.metadata["render_modes"]
        if render_mode is not None and render_mode not in render_modes:
            raise ValueError(f"render_mode must be None or one of {render_modes}, got {render_mode!r}.")
        self.n_hunters = n_hunters
        self.n_red_banks = n_red_banks
        self.n_blue_banks = n_blue_banks
        self.map_size = map_size
        self.max_cycles = max_cycles
        self.n_red_resources = n_red_resources
        self.n_blue_resources = n_blue_resources
        self.comm_range = comm_range
        self.max_neighbors = max_neighbors
        self.render_mode = render_mode
        self.regrowth_threshold = 2 * n_hunters
        group_sizes = (n_hunters, n_red_banks, n_blue_banks)
        self.possible_agents = [
            f"{name}_{i}" for name, size in zip(GROUP_NAMES, group_sizes, strict=True) for i in range(size)
        ]
        self.agents: list[str] = []
        self.group_ids = np.repeat(np.arange(3), group_sizes)
        self._n_resources = n_red_resources + n_blue_resources
        self._resource_colors = np.repeat([RED, BLUE], [n_red_resources, n_blue_resources])

        self._given_agent_cells = [
            _given_cells(cells, count, map_size, name)
            for cells, count, name in (
                (hunter_positions, n_hunters, "hunter_positions"),
                (red_bank_positions, n_red_banks, "red_bank_positions"),
                (blue_bank_positions, n_blue_banks, "blue_bank_positions"),
            )
        ]
        self._given_resource_cells = [
            _given_cells(cells, count, map_size, name)
            for cells, count, name in (
                (red_resource_positions, n_red_resources, "red_resource_positions"),
                (blue_resource_positions, n_blue_resources, "blue_resource_positions"),
            )
        ]
        self._given_treasure = [
            _given_treasure_map(red_treasure, map_size, "red_treasure"),
            _given_treasure_map(blue_treasure, map_size, "blue_treasure"),
        ]

        self._build_tables()
        hunter_space, bank_space = self._observation_boxes()
        self.groups = (
            AgentGroup("hunter", hunter_space, gym.spaces.Discrete(N_HUNTER_ACTIONS)),
            AgentGroup("red_bank", bank_space, gym.spaces.Discrete(N_BANK_ACTIONS)),
            AgentGroup("blue_bank", bank_space, gym.spaces.Discrete(N_BANK_ACTIONS)),
        )
        self.shared_observation_space = padded_observation_space(self.groups)
        self.shared_action_space = gym.spaces.Discrete(N_HUNTER_ACTIONS)

        self._rng: np.random.Generator | None = None
        self._cells = np.zeros(self.n_agents, dtype=np.int64)
        self._carried = np.zeros((n_hunters, 2), dtype=np.int64)
        self._agent_counts = np.zeros((3, self._n_cells), dtype=np.int64)
        self._resource_cells = np.zeros((self._n_resources, 2), dtype=np.int64)
        self._reserves = np.zeros(self._n_resources, dtype=np.int64)
        self._drops = np.zeros(2 * self._n_cells, dtype=np.int64)
        self._treasure_totals = np.zeros(2, dtype=np.int64)
        self._collected = 0
        self._delivered = np.zeros(2, dtype=np.int64)
        self._steps = 0
        self._episode_running = False

    # --- construction helpers -------------------------------------------------------------------
    def _build_tables(self) -> None:
        """Precompute the map layers, lookup tables and the per-agent gather offsets.

        Cells are addressed by flat index ``x * map_size + y``. ``self._layers`` ``(N_LAYERS, n_cells)``
        int8 holds one row per map layer (see the module constants), so every observation entry but
        the carried treasure is one gather ``layers.ravel()[cell + offset]`` with offsets
        ``self._offsets`` ``(n_agents, 357)`` (banks read the zero layer in their last 98 entries).
        """
        size = self.map_size
        self._n_cells = n_cells = size * size
        interior = np.zeros((size, size), dtype=bool)
        interior[WALL_WIDTH:-WALL_WIDTH, WALL_WIDTH:-WALL_WIDTH] = True
        self._interior = interior.ravel()
        self._n_wall_cells = int((~interior).sum())

        rows, columns = np.divmod(np.arange(n_cells), size)
        self._coordinates_of_cell = np.stack([rows, columns], axis=1)
        binary = binary_table(size, COORDINATE_BITS)
        self._layers = np.zeros((N_LAYERS, n_cells), dtype=np.int8)
        self._layers[X_BITS:] = np.concatenate([binary[rows], binary[columns]], axis=1).T
        self._bind_views()

        steps = np.arange(-(WINDOW // 2), WINDOW // 2 + 1)
        window = (steps[:, None] * size + steps[None, :]).ravel()
        position = np.arange(X_BITS, N_LAYERS) * n_cells
        hunter_offsets = np.concatenate([position, *(layer * n_cells + window for layer in HUNTER_CHANNELS)])
        bank_offsets = {
            group: np.concatenate(
                [
                    position,
                    *(layer * n_cells + window for layer in channels),
                    np.full(HUNTER_GATHER - BANK_OBS_DIM, ZERO * n_cells),
                ]
            )
            for group, channels in BANK_CHANNELS.items()
        }
        self._offsets = np.stack([hunter_offsets, bank_offsets[RED_BANK], bank_offsets[BLUE_BANK]])[
            self.group_ids
        ]
        box = np.arange(-1, 2)
        self._box = (box[:, None] * size + box[None, :]).ravel()  # the 3 x 3 neighbourhood
        self._n_actions_of_agent = np.where(self.group_ids == HUNTER, N_HUNTER_ACTIONS, N_BANK_ACTIONS)

        moves = np.array([-size, size, -1, 1, 0, 0, 0])
        targets = np.arange(n_cells)[:, None] + moves[None, :]
        stays = ~self._interior[np.clip(targets, 0, n_cells - 1)]
        self._next_cell = np.where(stays, np.arange(n_cells)[:, None], targets).ravel()

        padded = np.full((size + 2 * DROP_OFFSET, size + 2 * DROP_OFFSET), -1, dtype=np.int64)
        padded[DROP_OFFSET:-DROP_OFFSET, DROP_OFFSET:-DROP_OFFSET] = np.where(
            interior, np.arange(n_cells).reshape(size, size), -1
        )
        self._interior_cell_of_padded = padded  # flat interior cell at (x + 5, y + 5), else -1
        # Every (dx, dy, amount) a resource point can draw, with dx, dy stored as dx + 5, dy + 5.
        drop_span = 2 * DROP_OFFSET + 1
        n_amounts = DROP_RANGE[1] - DROP_RANGE[0] + 1
        drop_dx, drop_dy, drop_amount = np.unravel_index(
            np.arange(drop_span * drop_span * n_amounts), (drop_span, drop_span, n_amounts)
        )
        self._padded_drop_offsets = np.stack([drop_dx, drop_dy], axis=1)
        self._drop_amounts = drop_amount + DROP_RANGE[0]

    def _observation_boxes(self) -> tuple[gym.spaces.Box, gym.spaces.Box]:
        """Bounds of the hunter ``(359,)`` and bank ``(259,)`` observations (class docstring layout)."""
        hunter_low = np.zeros(HUNTER_OBS_DIM, dtype=np.int8)
        hunter_high = np.ones(HUNTER_OBS_DIM, dtype=np.int8)
        for channel, layer in enumerate(HUNTER_CHANNELS):
            window = _window_slice(channel)
            if layer in (RED_TREASURE, BLUE_TREASURE):
                hunter_low[window], hunter_high[window] = WALL, MAX_TREASURE_PER_CELL
            else:
                hunter_high[window] = MAX_COUNT
        hunter_high[HUNTER_GATHER:] = MAX_CARRY
        bank_low = np.zeros(BANK_OBS_DIM, dtype=np.int8)
        bank_high = np.full(BANK_OBS_DIM, MAX_COUNT, dtype=np.int8)
        bank_high[: 2 * COORDINATE_BITS] = 1
        treasure_window = _window_slice(BANK_CHANNELS[RED_BANK].index(RED_TREASURE))
        bank_low[treasure_window], bank_high[treasure_window] = WALL, MAX_TREASURE_PER_CELL
        return (
            gym.spaces.Box(low=hunter_low, high=hunter_high, dtype=np.int8),
            gym.spaces.Box(low=bank_low, high=bank_high, dtype=np.int8),
        )

    def _bind_views(self) -> None:
        """``_flat_layers``: ``_layers`` flat ``(N_LAYERS * n_cells,)``; ``_treasure``: its two treasure
        rows ``(2, n_cells)``."""
        self._flat_layers = self._layers.reshape(-1)
        self._treasure = self._layers[RED_TREASURE : BLUE_TREASURE + 1]

    # --- array API ------------------------------------------------------------------------------
    def reset_arrays(self, seed: int | None = None, options: dict | None = None) -> np.ndarray:
        """Start an episode. Returns observations ``(n_agents, 359)`` int8 (banks zero-padded).

        ``seed`` reseeds the generator; without it the first reset seeds from entropy and later
        resets continue the generator.
        """
        if seed is not None or self._rng is None:
            self._rng = np.random.default_rng(seed)
        group_sizes = (self.n_hunters, self.n_red_banks, self.n_blue_banks)
        self._cells = self._flat(
            np.concatenate(
                [
                    self._given_or_random_cells(given, count)
                    for given, count in zip(self._given_agent_cells, group_sizes, strict=True)
                ]
            )
        )
        self._resource_cells = np.concatenate(
            [
                self._given_or_random_cells(given, count)
                for given, count in zip(
                    self._given_resource_cells, (self.n_red_resources, self.n_blue_resources), strict=True
                )
            ]
        )
        self._reserves = self._rng.integers(RESERVE_RANGE[0], RESERVE_RANGE[1] + 1, size=self._n_resources)
        for color, given in enumerate(self._given_treasure):
            treasure = self._treasure[color].reshape(self.map_size, self.map_size)
            treasure[:] = WALL
            treasure[WALL_WIDTH:-WALL_WIDTH, WALL_WIDTH:-WALL_WIDTH] = 0 if given is None else given
        self._count_treasure()
        self._update_resource_layers()
        self._carried[:] = 0
        self._collected = 0
        self._delivered[:] = 0
        self._steps = 0
        self._episode_running = True
        self._neighbor_cache = None
        return self._observe()

    def step_arrays(
        self, actions: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """Advance one step with ``actions`` ``(n_agents,)``: hunters ``0..6``, banks ``0..4``.

        Returns ``(observations (n_agents, 359) int8, rewards (n_agents,) float32,
        terminated (n_agents,) bool, truncated (n_agents,) bool, team_info)``, ``team_info`` as in the
        class docstring.
        """
        if not self._episode_running:
            raise RuntimeError("step_arrays() called outside an episode; call reset_arrays() first.")
        actions = np.asarray(actions)
        if (
            actions.shape != (self.n_agents,)
            or actions.dtype.kind not in "iu"
            or actions.min() < 0
            or np.any(actions >= self._n_actions_of_agent)
        ):
            raise ValueError(
                f"actions must be an integer array of shape ({self.n_agents},) with values 0..6 for "
                "hunters and 0..4 for banks."
            )
        rewards = np.full(self.n_agents, STEP_REWARD)
        hunter_actions = actions[: self.n_hunters]
        self._collect(np.flatnonzero(hunter_actions == COLLECT), rewards)
        self._dump(np.flatnonzero(hunter_actions == DUMP), rewards)
        self._cells = self._next_cell[self._cells * N_HUNTER_ACTIONS + actions]
        if self._n_resources:
            self._regrow()
        self._steps += 1
        self._neighbor_cache = None
        truncated = self._steps >= self.max_cycles
        self._episode_running = not truncated
        team_info = {
            "collected": self._collected,
            "delivered_red": int(self._delivered[RED]),
            "delivered_blue": int(self._delivered[BLUE]),
            "treasure_on_map": int(self._treasure_totals.sum()),
            "carried": int(self._carried.sum()),
        }
        return (
            self._observe(),
            rewards.astype(np.float32),
            np.zeros(self.n_agents, dtype=bool),
            np.full(self.n_agents, truncated),
            team_info,
        )

    def _neighbor_lists(self) -> np.ndarray:
        """Agents of all groups within Chebyshev distance ``comm_range``: ``(n_agents, max_neighbors)`` int64.

        Row ``i`` is ``i`` itself, then its neighbours nearest first (ties by lower index); ``-1`` pads.
        """
        return grid_neighbors(self.agent_cells(), self.comm_range, self.max_neighbors)

    # --- state read-out (analysis, case studies) ------------------------------------------------
    def agent_cells(self) -> np.ndarray:
        """Agent cells ``(n_agents, 2)`` int64 as ``(x, y)``, hunters then red banks then blue banks."""
        return self._coordinates_of_cell[self._cells]

    def treasure_grid(self) -> np.ndarray:
        """Copy of the treasure maps ``(2, map_size, map_size)`` int8: red, blue; ``-1`` on walls."""
        return self._treasure.reshape(2, self.map_size, self.map_size).copy()

    def carried(self) -> np.ndarray:
        """Treasure carried by each hunter, ``(n_hunters, 2)`` int64: red, blue."""
        return self._carried.copy()

    def resource_cells(self) -> np.ndarray:
        """Resource point cells ``(n_red_resources + n_blue_resources, 2)`` int64 as ``(x, y)``, red first."""
        return self._resource_cells.copy()

    def resource_reserves(self) -> np.ndarray:
        """Treasure left at each resource point, ``(n_red_resources + n_blue_resources,)`` int64."""
        return self._reserves.copy()

    # --- dynamics -------------------------------------------------------------------------------
    def _collect(self, collectors: np.ndarray, rewards: np.ndarray) -> None:
        """Hunters ``collectors`` ``(n,)`` (ascending) pick up treasure; adds their rewards to ``rewards``.

        Sequential semantics without a loop over hunters: the collectors are grouped by cell (stable
        sort, so by index within a cell); of the items of a colour on the cell, a hunter takes
        ``clip(items - capacity of the earlier hunters on its cell, 0, own capacity)``, red first, then
        blue with the capacity left; the cell keeps what the last hunter of its group leaves.
        """
        if not collectors.size:
            return
        collectors = collectors[np.argsort(self._cells[collectors], kind="stable")]
        cells = self._cells[collectors]
        first = np.empty(cells.size, dtype=bool)
        first[0] = True
        np.not_equal(cells[1:], cells[:-1], out=first[1:])
        starts = np.flatnonzero(first)
        ends = np.append(starts[1:], cells.size) - 1
        group_starts = np.maximum.accumulate(np.where(first, np.arange(cells.size), 0))
        capacity = MAX_CARRY - self._carried[collectors].sum(axis=1)
        taken = np.empty((cells.size, 2), dtype=np.int64)
        for color in (RED, BLUE):
            earlier = np.cumsum(capacity) - capacity
            left = self._treasure[color, cells] - (earlier - earlier[group_starts])
            taken[:, color] = np.minimum(np.maximum(left, 0), capacity)
            capacity = capacity - taken[:, color]
            self._treasure[color, cells[ends]] = np.maximum(left[ends] - taken[ends, color], 0)
        self._carried[collectors] += taken
        rewards[collectors] += COLLECT_REWARD * taken.sum(axis=1)
        totals = taken.sum(axis=0)
        self._treasure_totals -= totals
        self._collected += int(totals.sum())

    def _dump(self, dumpers: np.ndarray, rewards: np.ndarray) -> None:
        """Hunters ``dumpers`` ``(n,)`` deliver to banks in their 3 x 3 neighbourhood; updates ``rewards``.

        Reads the bank counts per cell of the last observation, i.e. the banks before they move.
        """
        if not dumpers.size:
            return
        cells = self._cells[dumpers]
        nearby = self._agent_counts[RED_BANK:][:, cells[:, None] + self._box].sum(axis=2)  # (2, n)
        delivered = np.where(nearby > 0, self._carried[dumpers].T, 0)  # (2, n)
        if not delivered.any():
            return
        self._carried[dumpers] -= delivered.T
        rewards[dumpers] += DELIVERY_REWARD * delivered.sum(axis=0)
        self._delivered += delivered.sum(axis=1)
        # Each dumping hunter leaves items / k per colour on its cell; a bank collects the 3 x 3 sum.
        shares = np.bincount(
            (np.arange(2)[:, None] * self._n_cells + cells).ravel(),
            weights=(delivered / np.maximum(nearby, 1)).ravel(),
            minlength=2 * self._n_cells,
        )
        banks = slice(self.n_hunters, None)
        bank_keys = (self.group_ids[banks] - RED_BANK) * self._n_cells + self._cells[banks]
        rewards[banks] += DELIVERY_REWARD * shares[bank_keys[:, None] + self._box].sum(axis=1)

    def _regrow(self) -> None:
        """Resource points of each colour short of treasure drop some near themselves (class docstring)."""
        short = self._treasure_totals < self.regrowth_threshold
        points = np.flatnonzero(short[self._resource_colors])
        if not points.size:
            return
        draws = self._rng.integers(0, self._drop_amounts.size, size=points.size)
        targets = self._resource_cells[points] + self._padded_drop_offsets[draws]
        target_cells = self._interior_cell_of_padded[targets[:, 0], targets[:, 1]]
        inside = target_cells >= 0
        points, amounts = points[inside], self._drop_amounts[draws[inside]]
        keys = self._resource_colors[points] * self._n_cells + target_cells[inside]
        treasure = self._treasure.reshape(-1)
        np.add.at(self._drops, keys, amounts)
        treasure[keys] = np.minimum(treasure[keys] + self._drops[keys], MAX_TREASURE_PER_CELL)
        self._drops[keys] = 0
        self._count_treasure()
        self._reserves[points] -= amounts
        if self._reserves.min() <= 0:
            exhausted = np.flatnonzero(self._reserves <= 0)
            self._resource_cells[exhausted] = self._random_interior_cells(exhausted.size)
            self._reserves[exhausted] = self._rng.integers(
                RESERVE_RANGE[0], RESERVE_RANGE[1] + 1, size=exhausted.size
            )
            self._update_resource_layers()

    def _count_treasure(self) -> None:
        """Recount the treasure of each colour on the map (the layers hold ``-1`` on each wall cell)."""
        self._treasure_totals = self._treasure.sum(axis=1, dtype=np.int64) + self._n_wall_cells

    def _update_resource_layers(self) -> None:
        """Write the resource point counts per cell of both colours into their layers."""
        keys = self._resource_colors * self._n_cells + self._flat(self._resource_cells)
        counts = np.bincount(keys, minlength=2 * self._n_cells).reshape(2, self._n_cells)
        self._layers[RED_RESOURCES : BLUE_RESOURCES + 1] = np.minimum(counts, MAX_COUNT)

    # --- observation ----------------------------------------------------------------------------
    def _observe(self) -> np.ndarray:
        """Observations ``(n_agents, 359)`` int8 in the layout of the class docstring."""
        n_cells = self._n_cells
        counts = np.bincount(self.group_ids * n_cells + self._cells, minlength=3 * n_cells)
        self._agent_counts = counts.reshape(3, n_cells)
        self._layers[HUNTERS : BLUE_BANKS + 1] = np.minimum(self._agent_counts, MAX_COUNT)
        hunter_cells = self._cells[: self.n_hunters]
        carried = np.bincount(
            np.concatenate([hunter_cells, hunter_cells + n_cells]),
            weights=self._carried.T.ravel(),
            minlength=2 * n_cells,
        )
        self._layers[RED_CARRIED : BLUE_CARRIED + 1] = np.minimum(carried, MAX_COUNT).reshape(2, n_cells)
        observations = np.zeros((self.n_agents, HUNTER_OBS_DIM), dtype=np.int8)
        observations[:, :HUNTER_GATHER] = self._flat_layers.take(self._cells[:, None] + self._offsets)
        observations[: self.n_hunters, HUNTER_GATHER:] = self._carried
        return observations

    # --- placement helpers ----------------------------------------------------------------------
    def _flat(self, cells: np.ndarray) -> np.ndarray:
        """Flat map indices ``(n,)`` of cells ``(n, 2)``."""
        return cells[:, 0] * self.map_size + cells[:, 1]

    def _random_interior_cells(self, count: int) -> np.ndarray:
        """``(count, 2)`` uniformly random interior cells."""
        return self._rng.integers(WALL_WIDTH, self.map_size - WALL_WIDTH, size=(count, 2))

    def _given_or_random_cells(self, given: np.ndarray | None, count: int) -> np.ndarray:
        """A copy of the ``given`` cells ``(count, 2)``, or random interior ones."""
        return given.copy() if given is not None else self._random_interior_cells(count)

    # --- rendering ------------------------------------------------------------------------------
    def _draw(self) -> np.ndarray:
        """The current state as an image.

        The image is ``(8 * map_size, 8 * map_size, 3)`` uint8: walls grey, red treasure tints a cell
        red and blue treasure blue, resource points are dark red / dark blue cell outlines, banks red /
        blue squares and hunters small green squares on top; ``x`` runs downwards.
        """
        red, blue = np.maximum(self._treasure, 0).astype(np.int64)
        tint = red[:, None] * np.array([0, 40, 40]) + blue[:, None] * np.array([40, 40, 0])
        cell_colors = np.clip(255 - tint, 0, 255).astype(np.uint8)
        cell_colors[~self._interior] = _WALL_RGB
        cell_colors = cell_colors.reshape(self.map_size, self.map_size, 3)
        image = np.repeat(np.repeat(cell_colors, CELL_PIXELS, axis=0), CELL_PIXELS, axis=1)

        outline = np.ones((CELL_PIXELS, CELL_PIXELS), dtype=bool)
        outline[1:-1, 1:-1] = False
        square = np.zeros((CELL_PIXELS, CELL_PIXELS), dtype=bool)
        square[1:-1, 1:-1] = True
        dot = np.zeros((CELL_PIXELS, CELL_PIXELS), dtype=bool)
        dot[2:-2, 2:-2] = True
        resource_cells = self._flat(self._resource_cells)
        layers = [
            (resource_cells[self._resource_colors == color], _RESOURCE_RGB[color], outline)
            for color in (RED, BLUE)
        ]
        layers += [
            (self._cells[self.group_ids == group], _BANK_RGB[group - RED_BANK], square)
            for group in (RED_BANK, BLUE_BANK)
        ]
        layers.append((self._cells[self.group_ids == HUNTER], _HUNTER_RGB, dot))
        for flat_cells, color, shape in layers:
            marked = np.zeros(self._n_cells, dtype=bool)
            marked[flat_cells] = True
            image[np.kron(marked.reshape(self.map_size, self.map_size), shape).astype(bool)] = color
        return image


# --- argument checks ----------------------------------------------------------------------------
def _check_arguments(
    n_hunters: int,
    n_red_banks: int,
    n_blue_banks: int,
    map_size: int,
    max_cycles: int,
    n_red_resources: int,
    n_blue_resources: int,
    comm_range: int,
    max_neighbors: int,
) -> None:
    """Raise ``ValueError`` naming the argument, its valid range and its value for constructor arguments
    of a wrong type or outside their valid ranges."""
    check_agent_count("n_hunters", n_hunters)
    check_agent_count("n_red_banks", n_red_banks)
    check_agent_count("n_blue_banks", n_blue_banks)
    check_integer(
        "map_size",
        map_size,
        2 * WALL_WIDTH + 2,
        MAX_MAP_SIZE,
        f"a 3-cell wall ring around at least 2 x 2 cells; positions use {COORDINATE_BITS} bits",
    )
    check_integer("max_cycles", max_cycles, 1)
    check_integer("n_red_resources", n_red_resources, 0)
    check_integer("n_blue_resources", n_blue_resources, 0)
    check_number("comm_range", comm_range, 0)
    check_integer("max_neighbors", max_neighbors, 1)


def _given_cells(cells: np.ndarray | None, count: int, map_size: int, name: str) -> np.ndarray | None:
    """Validated copy ``(count, 2)`` int64 of user-given interior cells, or None."""
    if cells is None:
        return None
    array = np.asarray(cells)
    if array.shape != (count, 2) or not np.issubdtype(array.dtype, np.integer):
        raise ValueError(
            f"{name} must be an integer array of shape ({count}, 2), got {array.dtype} {array.shape}."
        )
    low, high = WALL_WIDTH, map_size - WALL_WIDTH - 1
    if array.size and (array.min() < low or array.max() > high):
        raise ValueError(f"{name} must be interior cells, each coordinate in {low}..{high}.")
    return array.astype(np.int64)


def _given_treasure_map(treasure: np.ndarray | None, map_size: int, name: str) -> np.ndarray | None:
    """Validated copy ``(map_size - 6, map_size - 6)`` int8 of a user-given interior treasure map, or None."""
    if treasure is None:
        return None
    array = np.asarray(treasure)
    interior = map_size - 2 * WALL_WIDTH
    if array.shape != (interior, interior) or not np.issubdtype(array.dtype, np.integer):
        raise ValueError(
            f"{name} must be an integer array of shape ({interior}, {interior}), "
            f"got {array.dtype} {array.shape}."
        )
    if array.min() < 0 or array.max() > MAX_TREASURE_PER_CELL:
        raise ValueError(f"{name} values must lie in 0..{MAX_TREASURE_PER_CELL}.")
    return array.astype(np.int8)


def parallel_env(**kwargs: Any) -> TreasureCollectionEnv:
    """Build a :class:`TreasureCollectionEnv` (PettingZoo-style module entry point)."""
    return TreasureCollectionEnv(**kwargs)
