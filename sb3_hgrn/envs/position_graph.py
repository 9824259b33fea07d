"""Communication graphs of agents at float positions, as fixed-width neighbour lists.

:class:`PositionGraph` links agents by Euclidean distance in any number of dimensions, optionally on
a torus, in one of three modes: the ``k`` nearest agents, every agent within a ``radius`` (the nearest
ones up to a list width), or the full graph. Its output is the neighbour-list format of every sb3_hgrn
env: row ``i`` of an ``(n_agents, max_neighbors)`` int64 array holds ``i`` itself, then its
neighbours nearest first (equal distances by lower index), padded with ``-1``. Agents that died or
left take no place in any list: only the living agents are linked.

Neighbours are found with a KD-tree (``scipy.spatial.cKDTree``): building it costs
``O(n log n)`` and each agent's query ``O(width log n)``, so in the ``k`` and radius modes the cost is
near-linear in the agent count and no ``n_agents x n_agents`` array is built. The full graph's lists
are ``n_agents`` wide by definition, so its output and cost grow with the square of the agent count.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.spatial import cKDTree

from sb3_hgrn.validation import is_integer, is_number


class PositionGraph:
    """Neighbour lists from agent positions, by k nearest neighbours, radius or the full graph.

    Args:
        n_agents: number of agents (at least 1).
        k: link every agent to its ``k`` nearest other agents (``k >= 1``); the lists are ``k + 1``
            wide and end in ``-1`` where fewer than ``k`` other agents exist.
        radius: link every agent to the other agents at Euclidean distance ``<= radius``, the
            nearest ``max_neighbors - 1`` of them when there are more.
        max_neighbors: list width in radius mode, the agent itself included (at least 1); required
            with ``radius`` and only there.
        world_size: side length of a toroidal world, one value for every axis or one per axis
            ``(dim,)``: positions are taken modulo it and distances follow the shortest way round.
            ``None`` (default): positions lie in an unbounded space.

    Without ``k`` and ``radius`` every agent lists all agents (width ``n_agents``).
    """

    def __init__(
        self,
        n_agents: int,
        k: int | None = None,
        radius: float | None = None,
        max_neighbors: int | None = None,
        world_size: float | Sequence[float] | None = None,
    ):
        if not is_integer(n_agents) or n_agents < 1:
            raise ValueError(f"n_agents must be a positive integer, got {n_agents!r}.")
        if k is not None and radius is not None:
            raise ValueError("Pass k (k nearest neighbours) or radius (neighbours within it), not both.")
        if k is not None and (not is_integer(k) or k < 1):
            raise ValueError(f"k must be a positive integer (neighbours besides the agent), got {k!r}.")
        if radius is not None and not _is_distance(radius):
            raise ValueError(f"radius must be a finite number >= 0, got {radius!r}.")
        if radius is None and max_neighbors is not None:
            raise ValueError(
                "max_neighbors is the list width of radius mode; with k the lists are k + 1 wide and "
                "the full graph's n_agents wide."
            )
        if radius is not None and (not is_integer(max_neighbors) or max_neighbors < 1):
            raise ValueError(
                f"radius needs max_neighbors, a positive integer: the list width, the agent itself "
                f"included; got {max_neighbors!r}."
            )
        self.n_agents = int(n_agents)
        self.k = None if k is None else int(k)
        self.radius = None if radius is None else float(radius)
        self.world_size = _world_size(world_size)
        if self.k is not None:
            self.max_neighbors = self.k + 1
        elif self.radius is not None:
            self.max_neighbors = int(max_neighbors)
        else:
            self.max_neighbors = self.n_agents

    def neighbors(self, positions: np.ndarray, alive: np.ndarray | None = None) -> np.ndarray:
        """Neighbour lists of agents at ``positions`` ``(n_agents, dim)`` (any real dtype).

        ``alive`` ``(n_agents,)`` bool names the agents still in the episode (``None``: all). Only
        living agents are linked: a gone agent takes no place in any list, its position is not read
        (it may be anything, ``nan`` included) and its own row holds only itself. The positions of
        the living agents must be finite.

        Returns ``(n_agents, max_neighbors)`` int64: row ``i`` starts with ``i``, then the living
        agents linked to ``i`` nearest first, equal distances by lower index (which of several agents
        at exactly the same distance makes the cut of a full row is unspecified); ``-1`` pads.
        """
        living = self._living(alive)
        points, sides = self._checked(positions, living)
        lists = np.full((self.n_agents, self.max_neighbors), -1, dtype=np.int64)
        lists[:, 0] = np.arange(self.n_agents)
        if len(living):
            among_living = self._lists_among(points, sides)
            lists[living] = np.append(living, -1)[among_living]  # entry -1 reads the appended -1
        return lists

    def _lists_among(self, points: np.ndarray, sides: np.ndarray | None) -> np.ndarray:
        """Neighbour lists ``(n_points, max_neighbors)`` int64 of ``points`` ``(n_points, dim)``
        (at least one), in their own numbering."""
        n_points = len(points)
        n_queried = min(self.max_neighbors, n_points)
        bound = np.inf if self.radius is None else np.nextafter(self.radius, np.inf)
        tree = cKDTree(points, boxsize=sides)
        distances, others = tree.query(points, k=n_queried, distance_upper_bound=bound)
        shape = (n_points, n_queried)  # a query for one neighbour returns 1-D arrays
        lists = _self_first_rows(distances.reshape(shape), others.reshape(shape))
        lists[lists == n_points] = -1  # cKDTree marks "none within the radius" with n_points
        if n_queried < self.max_neighbors:
            lists = np.pad(lists, ((0, 0), (0, self.max_neighbors - n_queried)), constant_values=-1)
        return lists

    def _living(self, alive: np.ndarray | None) -> np.ndarray:
        """Indices ``(n_living,)`` int64 of the living agents, ascending, from ``alive``."""
        if alive is None:
            return np.arange(self.n_agents)
        mask = np.asarray(alive)
        if mask.shape != (self.n_agents,) or mask.dtype != bool:
            raise ValueError(
                f"alive must be a bool array of shape (n_agents={self.n_agents},), got {mask.dtype} "
                f"{mask.shape}."
            )
        return np.flatnonzero(mask)

    def _checked(self, positions: np.ndarray, living: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """The positions of the ``living`` agents as float64 ``(n_living, dim)``, wrapped into the
        world if it is a torus, and the torus's sides ``(dim,)`` (``None`` without one)."""
        points = np.asarray(positions)
        if points.ndim != 2 or points.shape[0] != self.n_agents or points.shape[1] < 1:
            raise ValueError(
                f"positions must have shape (n_agents={self.n_agents}, dim), got {points.shape}."
            )
        if points.dtype.kind not in "biuf":
            raise ValueError(f"positions must be real numbers, got dtype {points.dtype}.")
        points = points[living].astype(np.float64)
        if not np.isfinite(points).all():
            raise ValueError("positions must be finite (no nan or inf) where agents are alive.")
        if self.world_size is None:
            return points, None
        if self.world_size.size not in (1, points.shape[1]):
            raise ValueError(
                f"world_size has {self.world_size.size} sides for positions of dim {points.shape[1]}."
            )
        sides = np.broadcast_to(self.world_size, points.shape[1:])
        wrapped = np.mod(points, sides)
        # np.mod of a tiny negative value can round up to the side itself, which the torus excludes.
        wrapped[wrapped >= sides] = 0.0
        return wrapped, sides


def _self_first_rows(distances: np.ndarray, others: np.ndarray) -> np.ndarray:
    """Reorder KD-tree results ``(n_agents, width)`` to the agent itself, then by distance and index.

    The tree lists each row by distance already, so only rows with a repeated finite distance (or
    without the agent first) are sorted again. Where the tree returned ``width`` other agents at
    distance 0 and not the agent itself, the agent takes the last place before the reordering.
    """
    owners = np.arange(len(others))[:, None]
    ties = (distances[:, 1:] == distances[:, :-1]) & np.isfinite(distances[:, 1:])
    rows = np.flatnonzero(ties.any(axis=1) | (others[:, 0] != owners[:, 0]))
    if len(rows):
        row_others, row_distances, row_owners = others[rows], distances[rows], owners[rows]
        missing_self = ~(row_others == row_owners).any(axis=1)
        row_others[missing_self, -1] = row_owners[missing_self, 0]
        row_distances[missing_self, -1] = 0.0
        order = np.lexsort((row_others, row_distances, row_others != row_owners), axis=-1)
        others[rows] = np.take_along_axis(row_others, order, axis=1)
    return others.astype(np.int64, copy=False)


def _world_size(world_size: float | Sequence[float] | None) -> np.ndarray | None:
    """``world_size`` as a float64 array of positive finite sides, or ``None``."""
    if world_size is None:
        return None
    sides = np.asarray(world_size, dtype=np.float64)
    if sides.ndim > 1 or sides.size == 0 or not (np.isfinite(sides).all() and (sides > 0).all()):
        raise ValueError(f"world_size must be a positive side length or one per axis, got {world_size!r}.")
    return sides


def _is_distance(value: object) -> bool:
    """Whether ``value`` is a finite real number ``>= 0``."""
    return is_number(value) and bool(np.isfinite(value)) and value >= 0
