"""UAV-MBS: UAVs acting as mobile base stations must cover clustered ground users (from the HGRN paper).

PettingZoo-style module: ``uav_mbs_v0.parallel_env(n_uavs=20)`` builds a :class:`UAVMBSEnv`.
"""

from __future__ import annotations

import math
from typing import Any

import gymnasium as gym
import numpy as np

from sb3_hgrn.envs.base import GraphParallelEnv, binary_table, check_agent_count
from sb3_hgrn.envs.graph import grid_neighbors
from sb3_hgrn.validation import check_integer, check_number

# Space and discretisation: positions in [0, 1]^2 map to cells int(p * 200 + 13), clipped to [13, 212],
# on a 226 x 226 raster whose 13-cell margin is obstacle.
GRID_CELLS = 200
MARGIN = 13
RASTER_SIZE = GRID_CELLS + 2 * MARGIN
FIRST_CELL, LAST_CELL = MARGIN, MARGIN + GRID_CELLS - 1
COORDINATE_BITS = 10
ID_BITS = 10
VIEW_RADIUS = 13

# Motion and energy.
MAX_SPEED = 0.02
FULL_THRUST = 0.02
HALF_THRUST = 0.01
BASE_ENERGY = 0.5
N_DIRECTIONS = 8  # E, SE, S, SW, W, NW, N, NE
N_ACTIONS = 2 * N_DIRECTIONS + 1  # full thrust, half thrust, then no thrust

# Reward.
SHARE_WEIGHT = 0.1
IDLE_REWARD = -1.0
BORDER_PENALTY = 1.0

# Users and UAV placement.
CLUSTER_CENTRE_RANGE = (0.15, 0.85)
MIN_CENTRE_DISTANCE = 0.25
USER_SPREAD = 0.1
UAV_START_RANGE = (0.1, 0.9)
CENTRE_DRAWS_PER_TRY = 64
MAX_CENTRE_TRIES = 100

# Compact observation.
COMPACT_NEIGHBORS = 5
COMPACT_USERS = 10

OBSERVATION_MODES = ("raster", "compact")
PIXELS_PER_CELL = 2
_OBSTACLE_RGB = (150, 150, 150)
_FREE_RGB = (255, 255, 255)
_USER_RGB = (40, 90, 230)
_COVERED_USER_RGB = (30, 160, 60)
_UAV_RGB = (220, 30, 30)
_COVERAGE_RGB = (245, 170, 170)


def view_offsets() -> np.ndarray:
    """The 527 cell offsets ``(dx, dy)`` of the local maps, ``(527, 2)`` int64, ``dx`` slowest.

    They are the integer offsets with ``dx**2 + dy**2 <= 13**2`` and ``-13 <= dx, dy <= 12``: the closed
    disc of radius 13 (529 offsets) without its two extreme points ``(13, 0)`` and ``(0, 13)``, i.e. the
    disc cut to the half-open window ``[-13, 13)`` per axis. No disc centred on a cell has 527 offsets
    (their counts are ``1 + 4k``); this window reproduces the paper's observation size of 1,613.
    """
    steps = np.arange(-VIEW_RADIUS, VIEW_RADIUS)
    dx, dy = np.meshgrid(steps, steps, indexing="ij")
    inside = dx**2 + dy**2 <= VIEW_RADIUS**2
    return np.stack([dx[inside], dy[inside]], axis=1)


def connected_component_labels(adjacency: np.ndarray) -> np.ndarray:
    """Component labels of an undirected graph given as a dense ``(n, n)`` bool adjacency matrix.

    The diagonal must be ``True``. Returns ``(n,)`` int64: the lowest node index of each node's
    component. Vectorised min-label propagation with pointer jumping (union-find by hooking onto the
    lowest label, with path halving): each round is one masked row minimum, and about
    ``log2(diameter)`` rounds are needed. For the graphs of this env (tens of nodes) it is about ten
    times faster than ``scipy.sparse.csgraph.connected_components``, whose input checks alone take
    about 75 us.
    """
    n_nodes = len(adjacency)
    labels = np.arange(n_nodes)
    while True:
        hooked = np.where(adjacency, labels[None, :], n_nodes).min(axis=1)
        hooked = hooked[hooked]
        if np.array_equal(hooked, labels):
            return labels
        labels = hooked


class UAVMBSEnv(GraphParallelEnv):
    """UAV-MBS: ``n_uavs`` UAVs move over ``[0, 1]^2`` to cover ``n_users`` static ground users.

    Coordinates: a position ``p = (x, y)`` lies in ``[0, 1]^2``, ``x`` east and ``y`` north. Maps,
    graph and rewards use cells ``int(p * 200 + 13)`` per axis, clipped to ``[13, 212]``, on a
    ``226 x 226`` raster whose 13-cell margin is obstacle; distances in cells are Euclidean on cell
    indices.

    Rules, per step:

    * Action ``a`` in ``0..16``: ``0..7`` thrust ``F`` of 0.02 towards E, SE, S, SW, W, NW, N, NE (unit
      directions, diagonals normalised), ``8..15`` the same at half thrust 0.01, 16 no thrust.
    * ``v <- v + F``; if ``|v| > 0.02``, ``v`` is rescaled to length 0.02 (the original zeroed ``v``
      when ``|v|`` was exactly 0.02, so axis-aligned full thrust from rest did nothing; fixed). Then
      ``p <- clip(p + v, 0, 1)``. The velocity is kept when clipped. A UAV is *pressed against the
      border* this step when the unclipped ``p + v`` leaves ``[0, 1]`` on some axis.
    * Energy ``e = 0.5 + 0.5 * |v| / 0.02`` in ``[0.5, 1]`` (``v`` after the cap).
    * Comm graph: UAVs within ``comm_range`` cells (``dx**2 + dy**2 <= comm_range**2``). ``G(i)`` is
      the connected component of UAV ``i`` in the full graph (not cut to ``max_neighbors``).
    * A user is covered by a UAV within ``coverage_range`` cells (``dx**2 + dy**2 < coverage_range**2``).
      ``individual_i`` = users covered by ``i`` and by no other UAV of ``G(i)``; ``total_i`` = users
      covered by any UAV of ``G(i)``. The reward is::

          r_i = ( (individual_i if individual_i > 0 else -1)
                  + (0.1 * (total_i - individual_i) / (|G(i)| - 1) if |G(i)| > 1 else 0)
                  - (1 if pressed against the border else 0) ) / e_i

    Users: ``n_clusters`` centres uniform in ``[0.15, 0.85]^2`` at pairwise distance >= 0.25 (rejection
    sampling); user ``k`` belongs to centre ``k % n_clusters`` and lies at centre + N(0, 0.1^2) per axis,
    clipped to ``[0, 1]``. UAVs start uniform in ``[0.1, 0.9]^2`` at rest. Episodes end by truncation
    after ``max_cycles`` steps.

    Observation, float32. ``observation_mode="raster"`` (default), 1,613 entries; binary numbers
    most significant bit first; the maps are sampled at ``cell + offset`` for the 527 offsets of
    :func:`view_offsets` (``dx`` slowest):

    ==================  ==================================  =========================================
    slice               content                             values
    ==================  ==================================  =========================================
    ``[0:10]``          own ``x`` cell in binary            0/1
    ``[10:20]``         own ``y`` cell in binary            0/1
    ``[20:547]``        UAVs per cell, self included        count >= 0 (self: >= 1)
    ``[547:1074]``      users per cell                      count >= 0
    ``[1074:1601]``     obstacle flag (outside [13, 212])   0/1
    ``[1601:1603]``     velocity / 0.02                     [-1, 1]
    ``[1603:1613]``     agent index in binary               0/1, fixed width 10
    ==================  ==================================  =========================================

    The space (size and bounds) does not depend on ``n_uavs`` (at most 1,024) or ``n_users``, so a
    policy transfers between UAV counts.

    ``observation_mode="compact"``, 44 entries, zero where fewer neighbours or users exist:

    ==================  ==================================================================
    slice               content
    ==================  ==================================================================
    ``[0:2]``           own position ``p`` in [0, 1]
    ``[2:4]``           own velocity / 0.02 in [-1, 1]
    ``[4:24]``          5 nearest neighbour UAVs in comm range (nearest first, ties by lower
                        index), each ``(dx, dy) / comm_range`` in cells, in [-1, 1], then
                        ``(v_j - v_i) / 0.02`` in [-2, 2]
    ``[24:44]``         10 nearest users within coverage range (nearest first, ties by lower
                        index), each ``(dx, dy) / coverage_range`` in cells, in (-1, 1)
    ==================  ==================================================================

    Graph: :meth:`neighbors` lists the UAVs within ``comm_range`` (self first, nearest first, ties by
    lower index), cut to the ``max_neighbors`` nearest, see :func:`sb3_hgrn.envs.graph.grid_neighbors`.

    ``team_info`` after each step: ``coverage`` = mean over users of (steps so far in which the user
    was covered by any UAV) / (steps so far); ``fairness`` = Jain index ``(sum c)^2 / (n_users * sum
    c^2)`` of those per-user counts ``c`` (0 while no user has been covered); ``energy`` = mean ``e``
    over UAVs this step.

    A hand-made configuration (case study) is built from ``uav_positions`` ``(n_uavs, 2)`` and
    ``user_positions`` ``(n_users, 2)`` in ``[0, 1]``; each one given replaces the random placement at
    every reset.
    """

    metadata: dict[str, Any] = {
        "render_modes": ["rgb_array", "human"],
        "name": "uav_mbs_v0",
        "render_fps": 10,
    }

    def __init__(
        self,
        n_uavs: int = 20,
        n_users: int = 120,
        n_clusters: int = 3,
        max_cycles: int = 100,
        comm_range: float = 18,
        coverage_range: float = 10,
        max_neighbors: int = 16,
        observation_mode: str = "raster",
        render_mode: str | None = None,
        uav_positions: np.ndarray | None = None,
        user_positions: np.ndarray | None = None,
    ) -> None:
        _check_arguments(n_uavs, n_users, n_clusters, max_cycles, comm_range, coverage_range, max_neighbors)
        if observation_mode not in OBSERVATION_MODES:
            raise ValueError(
                f"observation_mode must be one of {OBSERVATION_MODES}, got {observation_mode!r}."
            )
        render_modes = self.metadata["render_modes"]
        if render_mode is not None and render_mode not in render_modes:
            raise ValueError(f"render_mode must be None or one of {render_modes}, got {render_mode!r}.")
        self.n_users = n_users
        self.n_clusters = n_clusters
        self.max_cycles = max_cycles
        self.comm_range = comm_range
        self.coverage_range = coverage_range
        self.max_neighbors = max_neighbors
        self.observation_mode = observation_mode
        self.render_mode = render_mode
        self.possible_agents = [f"uav_{i}" for i in range(n_uavs)]
        self.agents: list[str] = []
        self._given_uav_positions = _given_positions(uav_positions, n_uavs, "uav_positions")
        self._given_user_positions = _given_positions(user_positions, n_users, "user_positions")

        self._build_tables()
        self.shared_observation_space = self._observation_box()
        self.shared_action_space = gym.spaces.Discrete(N_ACTIONS)

        self._rng: np.random.Generator | None = None
        self._positions = np.zeros((n_uavs, 2))
        self._velocities = np.zeros((n_uavs, 2))
        self._cells = np.zeros((n_uavs, 2), dtype=np.int64)
        self._flat_cells = np.zeros(n_uavs, dtype=np.int64)
        self._user_positions = np.zeros((n_users, 2))
        self._user_cells = np.zeros((n_users, 2), dtype=np.int64)
        self._covered_steps = np.zeros(n_users, dtype=np.int64)
        self._steps = 0
        self._episode_running = False

    # --- construction helpers -------------------------------------------------------------------
    def _build_tables(self) -> None:
        """Precompute thrusts, raster layers, gather offsets and the observation template.

        Raster cells are addressed by flat index ``x * 226 + y``. ``self._layers`` ``(3, 226**2)``
        float32 holds the UAV counts (updated every step), the user counts (set at reset) and the
        obstacle flags, so the three local maps of all UAVs are one gather from it.
        """
        angles = -np.arange(N_DIRECTIONS) * (2 * np.pi / N_DIRECTIONS)  # E, SE, S, ... clockwise from east
        directions = np.stack([np.cos(angles), np.sin(angles)], axis=1)
        directions[np.abs(directions) < 1e-12] = 0.0
        self._thrusts = np.concatenate([FULL_THRUST * directions, HALF_THRUST * directions, np.zeros((1, 2))])

        n_cells = RASTER_SIZE * RASTER_SIZE
        self._layers = np.zeros((3, n_cells), dtype=np.float32)
        rows, columns = np.divmod(np.arange(n_cells), RASTER_SIZE)
        valid = (rows >= FIRST_CELL) & (rows <= LAST_CELL) & (columns >= FIRST_CELL) & (columns <= LAST_CELL)
        self._layers[2] = ~valid
        self._bind_views()

        offsets = view_offsets()
        flat_offsets = offsets[:, 0] * RASTER_SIZE + offsets[:, 1]
        self._gather_offsets = (np.arange(3)[:, None] * n_cells + flat_offsets[None, :]).ravel()
        self._gather_indices = np.empty((self.n_agents, self._gather_offsets.size), dtype=np.int64)
        self._coordinate_bits = binary_table(RASTER_SIZE, COORDINATE_BITS, np.float32)

        maps_start = 2 * COORDINATE_BITS
        self._maps_slice = slice(maps_start, maps_start + self._gather_offsets.size)
        self._velocity_slice = slice(self._maps_slice.stop, self._maps_slice.stop + 2)
        raster_dim = self._velocity_slice.stop + ID_BITS
        compact_dim = 4 + 4 * COMPACT_NEIGHBORS + 2 * COMPACT_USERS
        self.obs_dim = raster_dim if self.observation_mode == "raster" else compact_dim
        self._observation_template = np.zeros((self.n_agents, self.obs_dim), dtype=np.float32)
        if self.observation_mode == "raster":
            self._observation_template[:, self._velocity_slice.stop :] = binary_table(
                self.n_agents, ID_BITS, np.float32
            )

    def _observation_box(self) -> gym.spaces.Box:
        """Bounds of each observation entry, in the layouts of the class docstring."""
        low = np.zeros(self.obs_dim, dtype=np.float32)
        high = np.ones(self.obs_dim, dtype=np.float32)
        if self.observation_mode == "raster":
            # Counts are left unbounded, so the space does not depend on n_uavs or n_users and a model
            # trained with one UAV count loads onto an env with another.
            n_offsets = self._gather_offsets.size // 3
            high[self._maps_slice][: 2 * n_offsets] = np.inf
            low[self._velocity_slice] = -1.0
        else:
            low[2:] = -1.0
            neighbor_slice = slice(4, 4 + 4 * COMPACT_NEIGHBORS)
            low[neighbor_slice].reshape(COMPACT_NEIGHBORS, 4)[:, 2:] = -2.0
            high[neighbor_slice].reshape(COMPACT_NEIGHBORS, 4)[:, 2:] = 2.0
        return gym.spaces.Box(low=low, high=high, dtype=np.float32)

    def _bind_views(self) -> None:
        """``_uav_count_layer``, ``_user_count_layer``: the first two rows of ``_layers`` ``(n_cells,)``."""
        self._uav_count_layer, self._user_count_layer = self._layers[0], self._layers[1]

    # --- array API ------------------------------------------------------------------------------
    def reset_arrays(self, seed: int | None = None, options: dict | None = None) -> np.ndarray:
        """Start an episode. Returns observations ``(n_uavs, obs_dim)`` float32.

        ``seed`` reseeds the generator; without it the first reset seeds from entropy and later
        resets continue the generator.
        """
        if seed is not None or self._rng is None:
            self._rng = np.random.default_rng(seed)
        if self._given_user_positions is not None:
            self._user_positions = self._given_user_positions.copy()
        else:
            self._user_positions = self._random_user_positions()
        self._user_cells = _cells_of(self._user_positions)
        self._user_count_layer[:] = np.bincount(
            self._user_cells[:, 0] * RASTER_SIZE + self._user_cells[:, 1], minlength=RASTER_SIZE**2
        )
        if self._given_uav_positions is not None:
            self._positions = self._given_uav_positions.copy()
        else:
            self._positions = self._rng.uniform(*UAV_START_RANGE, size=(self.n_agents, 2))
        self._velocities = np.zeros((self.n_agents, 2))
        self._move_cells()
        self._covered_steps[:] = 0
        self._steps = 0
        self._episode_running = True
        return self._observe()

    def step_arrays(
        self, actions: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """Advance one step with ``actions`` ``(n_uavs,)`` in ``0..16``.

        Returns ``(observations (n_uavs, obs_dim) float32, rewards (n_uavs,) float32,
        terminated (n_uavs,) bool, truncated (n_uavs,) bool, team_info)`` with ``team_info =
        {"coverage": float, "fairness": float, "energy": float}`` (see the class docstring).
        """
        if not self._episode_running:
            raise RuntimeError("step_arrays() called outside an episode; call reset_arrays() first.")
        actions = np.asarray(actions)
        if actions.shape != (self.n_agents,) or actions.min() < 0 or actions.max() >= N_ACTIONS:
            raise ValueError(
                f"actions must be an integer array of shape ({self.n_agents},) with values in 0..16."
            )
        velocities = self._velocities + self._thrusts[actions]
        speeds = np.hypot(velocities[:, 0], velocities[:, 1])
        capped_speeds = np.minimum(speeds, MAX_SPEED)
        # 1 up to the speed cap (so v is kept exactly), MAX_SPEED / |v| above it.
        velocities *= (MAX_SPEED / np.maximum(speeds, MAX_SPEED))[:, None]
        energies = BASE_ENERGY + (1.0 - BASE_ENERGY) / MAX_SPEED * capped_speeds
        unclipped = self._positions + velocities
        self._positions = np.minimum(np.maximum(unclipped, 0.0), 1.0)
        pressed = np.logical_or.reduce(self._positions != unclipped, axis=1)
        self._velocities = velocities
        self._move_cells()

        coverage_rewards, covered_users = self._coverage_rewards()
        rewards = (coverage_rewards - BORDER_PENALTY * pressed) / energies
        self._covered_steps += covered_users
        self._steps += 1
        truncated = self._steps >= self.max_cycles
        self._episode_running = not truncated
        return (
            self._observe(),
            rewards.astype(np.float32),
            np.zeros(self.n_agents, dtype=bool),
            np.full(self.n_agents, truncated),
            self._team_info(float(energies.mean())),
        )

    def _neighbor_lists(self) -> np.ndarray:
        """UAVs within ``comm_range`` cells (Euclidean): ``(n_uavs, max_neighbors)`` int64.

        Row ``i`` is ``i`` itself, then its neighbours nearest first (ties by lower index), cut to
        ``max_neighbors`` entries; ``-1`` pads.
        """
        return grid_neighbors(self._cells, self.comm_range, self.max_neighbors, metric="euclidean")

    # --- state read-out (analysis, case studies) ------------------------------------------------
    def uav_positions(self) -> np.ndarray:
        """UAV positions ``(n_uavs, 2)`` float64 as ``(x, y)`` in ``[0, 1]``."""
        return self._positions.copy()

    def uav_velocities(self) -> np.ndarray:
        """UAV velocities ``(n_uavs, 2)`` float64."""
        return self._velocities.copy()

    def uav_cells(self) -> np.ndarray:
        """UAV cells ``(n_uavs, 2)`` int64 in ``[13, 212]``."""
        return self._cells.copy()

    def user_positions(self) -> np.ndarray:
        """User positions ``(n_users, 2)`` float64 in ``[0, 1]``."""
        return self._user_positions.copy()

    def user_cells(self) -> np.ndarray:
        """User cells ``(n_users, 2)`` int64 in ``[13, 212]``."""
        return self._user_cells.copy()

    # --- dynamics -------------------------------------------------------------------------------
    def _move_cells(self) -> None:
        """Recompute the UAV cells, the UAV count layer and the UAV-UAV and UAV-user offsets after a move.

        Offsets are ``[i, j] = cell_j - cell_i`` per axis (``(n_uavs, n_uavs)`` and ``(n_uavs, n_users)``
        int64), with their squared lengths.
        """
        self._cells = _cells_of(self._positions)
        uav_x, uav_y = self._cells[:, 0], self._cells[:, 1]
        self._uav_dx, self._uav_dy, self._uav_squared_distances = _pair_offsets(uav_x, uav_y, uav_x, uav_y)
        self._user_dx, self._user_dy, self._user_squared_distances = _pair_offsets(
            uav_x, uav_y, self._user_cells[:, 0], self._user_cells[:, 1]
        )
        self._uav_count_layer[self._flat_cells] = 0.0
        self._flat_cells = uav_x * RASTER_SIZE + uav_y
        self._uav_count_layer[self._flat_cells] = np.count_nonzero(self._uav_squared_distances == 0, axis=1)
        self._neighbor_cache = None

    def _coverage_rewards(self) -> tuple[np.ndarray, np.ndarray]:
        """The coverage part of the rewards and the users covered by any UAV.

        Returns ``(n_uavs,)`` float64 (the reward before the border penalty and the energy division)
        and ``(n_users,)`` bool.
        """
        covers = self._user_squared_distances < self.coverage_range**2  # (n_uavs, n_users)
        labels = connected_component_labels(self._uav_squared_distances <= self.comm_range**2)
        same_component = labels[:, None] == labels[None, :]  # (n_uavs, n_uavs)
        # [i, u]: how many UAVs of G(i) cover user u.
        coverers_in_component = same_component.astype(np.float32) @ covers.astype(np.float32)
        individual = np.count_nonzero(covers & (coverers_in_component == 1), axis=1)
        total = np.count_nonzero(coverers_in_component, axis=1)
        others = np.count_nonzero(same_component, axis=1) - 1
        shared = SHARE_WEIGHT * (total - individual) / np.maximum(others, 1)
        covered_users = np.logical_or.reduce(covers, axis=0)
        return np.where(individual > 0, individual, IDLE_REWARD) + shared, covered_users

    def _team_info(self, mean_energy: float) -> dict[str, float]:
        """Coverage, Jain fairness and mean energy (see the class docstring)."""
        covered_steps = self._covered_steps
        total = int(covered_steps.sum())
        squares = int(covered_steps @ covered_steps)
        return {
            "coverage": total / (self.n_users * self._steps),
            "fairness": total * total / (self.n_users * squares) if squares else 0.0,
            "energy": mean_energy,
        }

    # --- observation ----------------------------------------------------------------------------
    def _observe(self) -> np.ndarray:
        """Observations ``(n_uavs, obs_dim)`` float32 in the layout of ``observation_mode``."""
        if self.observation_mode == "compact":
            return self._observe_compact()
        observations = self._observation_template.copy()
        observations[:, :COORDINATE_BITS] = self._coordinate_bits[self._cells[:, 0]]
        observations[:, COORDINATE_BITS : 2 * COORDINATE_BITS] = self._coordinate_bits[self._cells[:, 1]]
        np.add(self._flat_cells[:, None], self._gather_offsets[None, :], out=self._gather_indices)
        observations[:, self._maps_slice] = self._layers.reshape(-1)[self._gather_indices]
        observations[:, self._velocity_slice] = self._velocities / MAX_SPEED
        return observations

    def _observe_compact(self) -> np.ndarray:
        """Compact observations ``(n_uavs, 44)`` float32 (see the class docstring)."""
        n_uavs = self.n_agents
        observations = self._observation_template.copy()
        observations[:, 0:2] = self._positions
        observations[:, 2:4] = self._velocities / MAX_SPEED

        out_of_range = np.iinfo(np.int64).max
        neighbor_keys = np.where(
            self._uav_squared_distances <= self.comm_range**2, self._uav_squared_distances, out_of_range
        )
        neighbor_keys[np.arange(n_uavs), np.arange(n_uavs)] = out_of_range
        n_kept = min(COMPACT_NEIGHBORS, n_uavs - 1)
        nearest = np.argsort(neighbor_keys, axis=1, kind="stable")[:, :n_kept]
        present = np.take_along_axis(neighbor_keys, nearest, axis=1) < out_of_range
        rows = np.arange(n_uavs)[:, None]
        neighbors = np.concatenate(
            [
                np.stack([self._uav_dx[rows, nearest], self._uav_dy[rows, nearest]], axis=2)
                / self.comm_range,
                (self._velocities[nearest] - self._velocities[:, None, :]) / MAX_SPEED,
            ],
            axis=2,
        )
        neighbors = np.where(present[:, :, None], neighbors, 0.0)
        observations[:, 4 : 4 + 4 * n_kept] = neighbors.reshape(n_uavs, -1)

        user_keys = np.where(
            self._user_squared_distances < self.coverage_range**2, self._user_squared_distances, out_of_range
        )
        n_kept = min(COMPACT_USERS, self.n_users)
        nearest = np.argsort(user_keys, axis=1, kind="stable")[:, :n_kept]
        present = np.take_along_axis(user_keys, nearest, axis=1) < out_of_range
        users = np.stack([self._user_dx[rows, nearest], self._user_dy[rows, nearest]], axis=2)
        users = np.where(present[:, :, None], users / self.coverage_range, 0.0)
        users_start = 4 + 4 * COMPACT_NEIGHBORS
        observations[:, users_start : users_start + 2 * n_kept] = users.reshape(n_uavs, -1)
        return observations

    # --- placement helpers ----------------------------------------------------------------------
    def _random_user_positions(self) -> np.ndarray:
        """``(n_users, 2)`` users around ``n_clusters`` well-separated centres (see the class docstring)."""
        centres = self._cluster_centres()
        cluster_of_user = np.arange(self.n_users) % self.n_clusters
        jitter = self._rng.normal(0.0, USER_SPREAD, size=(self.n_users, 2))
        return np.clip(centres[cluster_of_user] + jitter, 0.0, 1.0)

    def _cluster_centres(self) -> np.ndarray:
        """``(n_clusters, 2)`` centres uniform in ``[0.15, 0.85]^2`` at pairwise distance >= 0.25.

        Centres are drawn one after the other, each from a batch of candidates (the first far enough
        from the earlier centres); if a batch has no such candidate, all centres are drawn again.
        """
        for _ in range(MAX_CENTRE_TRIES):
            centres = np.empty((0, 2))
            for _ in range(self.n_clusters):
                candidates = self._rng.uniform(*CLUSTER_CENTRE_RANGE, size=(CENTRE_DRAWS_PER_TRY, 2))
                distances = np.linalg.norm(candidates[:, None, :] - centres[None, :, :], axis=2)
                far_enough = np.flatnonzero((distances >= MIN_CENTRE_DISTANCE).all(axis=1))
                if far_enough.size == 0:
                    break
                centres = np.vstack([centres, candidates[far_enough[:1]]])
            else:
                return centres
        raise RuntimeError(
            f"Could not place {self.n_clusters} cluster centres at pairwise distance >= "
            f"{MIN_CENTRE_DISTANCE} in {CLUSTER_CENTRE_RANGE}^2; use fewer clusters."
        )

    # --- rendering ------------------------------------------------------------------------------
    def _draw(self) -> np.ndarray:
        """The current state as an image.

        The image is ``(452, 452, 3)`` uint8, 2 pixels per raster cell, ``x`` to the right and ``y``
        upwards: obstacle margin grey, coverage discs light red, users blue (green when covered), UAVs
        red.
        """
        size = RASTER_SIZE * PIXELS_PER_CELL
        image = np.empty((size, size, 3), dtype=np.uint8)
        image[:] = _OBSTACLE_RGB
        free = slice(FIRST_CELL * PIXELS_PER_CELL, (LAST_CELL + 1) * PIXELS_PER_CELL)
        image[free, free] = _FREE_RGB

        def paint(cells: np.ndarray, offsets: np.ndarray, color: tuple[int, int, int]) -> None:
            """Paint pixels ``offsets`` ``(k, 2)`` around the centre pixel of each of ``cells``."""
            centres = cells * PIXELS_PER_CELL + PIXELS_PER_CELL // 2
            pixels = np.clip((centres[:, None, :] + offsets[None, :, :]).reshape(-1, 2), 0, size - 1)
            image[size - 1 - pixels[:, 1], pixels[:, 0]] = color

        disc_radius = self.coverage_range * PIXELS_PER_CELL
        paint(self._cells, _disc_pixel_offsets(disc_radius), _COVERAGE_RGB)
        dot = _disc_pixel_offsets(1.5)
        covered = self._user_squared_distances.min(axis=0) < self.coverage_range**2
        paint(self._user_cells[~covered], dot, _USER_RGB)
        paint(self._user_cells[covered], dot, _COVERED_USER_RGB)
        paint(self._cells, _disc_pixel_offsets(3.5), _UAV_RGB)
        return image


def _cells_of(positions: np.ndarray) -> np.ndarray:
    """Raster cells ``(n, 2)`` int64 of positions ``(n, 2)`` in ``[0, 1]``: ``int(p * 200 + 13)`` clipped.

    Only ``p = 1`` needs the clip (to 212); ``p >= 0`` already gives cells ``>= 13``.
    """
    return np.minimum((positions * GRID_CELLS + MARGIN).astype(np.int64), LAST_CELL)


def _pair_offsets(
    from_x: np.ndarray, from_y: np.ndarray, to_x: np.ndarray, to_y: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Offsets ``dx, dy`` ``(n_from, n_to)`` with ``[i, j] = to_j - from_i`` and ``dx**2 + dy**2``."""
    dx = to_x[None, :] - from_x[:, None]
    dy = to_y[None, :] - from_y[:, None]
    return dx, dy, dx * dx + dy * dy


def _disc_pixel_offsets(radius: float) -> np.ndarray:
    """Integer pixel offsets ``(k, 2)`` with ``dx**2 + dy**2 <= radius**2``."""
    reach = math.floor(radius)
    steps = np.arange(-reach, reach + 1)
    dx, dy = np.meshgrid(steps, steps, indexing="ij")
    inside = dx**2 + dy**2 <= radius**2
    return np.stack([dx[inside], dy[inside]], axis=1)


# --- argument checks ----------------------------------------------------------------------------
def _check_arguments(
    n_uavs: int,
    n_users: int,
    n_clusters: int,
    max_cycles: int,
    comm_range: float,
    coverage_range: float,
    max_neighbors: int,
) -> None:
    """Raise ``ValueError`` naming the argument, its valid range and its value for constructor arguments
    of a wrong type or outside their valid ranges."""
    check_agent_count("n_uavs", n_uavs, 2**ID_BITS, f"the index bits are {ID_BITS} wide")
    check_integer("n_users", n_users, 1)
    check_integer("n_clusters", n_clusters, 1, n_users, "at most one cluster per user")
    check_integer("max_cycles", max_cycles, 1)
    check_number("comm_range", comm_range, 0, strict=True)
    check_number("coverage_range", coverage_range, 0, strict=True)
    check_integer("max_neighbors", max_neighbors, 1)


def _given_positions(positions: np.ndarray | None, count: int, name: str) -> np.ndarray | None:
    """Validated copy ``(count, 2)`` float64 of user-given positions in ``[0, 1]``, or None."""
    if positions is None:
        return None
    array = np.asarray(positions, dtype=np.float64)
    if array.shape != (count, 2):
        raise ValueError(f"{name} must have shape ({count}, 2), got {array.shape}.")
    if not np.all((array >= 0.0) & (array <= 1.0)):
        raise ValueError(f"{name} must lie in [0, 1] (NaN not allowed).")
    return array


def parallel_env(**kwargs: Any) -> UAVMBSEnv:
    """Build a :class:`UAVMBSEnv` (PettingZoo-style module entry point)."""
    return UAVMBSEnv(**kwargs)
