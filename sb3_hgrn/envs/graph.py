"""Communication graphs of agents on an integer grid, as fixed-width neighbour lists.

:func:`grid_neighbors` is shared by every environment whose agents live on grid cells. Its output
is the neighbour-list format used throughout sb3_hgrn: row ``i`` of an ``(n_agents, max_neighbors)``
int64 array holds ``i`` itself, then the agents within range of ``i`` nearest first (ties by lower
index), padded with ``-1``.

Ordering: every pair gets an integer *rank*: 0 for the agent itself, ``1 + distance key`` for an agent
in range (the key is ``max(|dx|, |dy|)`` for Chebyshev, ``dx**2 + dy**2`` for Euclidean distance, both
exact on integer cells), and rows are sorted by ``(rank, index)``.

:func:`living_neighbors` and :func:`subgraph` cut such lists down to the living agents or to a subset
of the agents.
"""

from __future__ import annotations

import math

import numpy as np

METRICS = ("chebyshev", "euclidean")

# Up to this many agents (and while its packed keys fit in int32), one (n_agents, n_agents) matrix of
# sort keys is built and sorted row by row; otherwise agents are bucketed into square blocks and only
# the 3 x 3 blocks around each agent are searched, so cost and memory grow linearly. Measured with
# int32 keys on a 2-core AMD EPYC (AVX2; Chebyshev radius 3, about 6 agents in range), dense against
# blocked: 53 us against 108 us at 100 agents, 66 against 119 at 128, 122 against 123 at 140, 1,007
# against 172 at 256 (numpy's vectorised sort is fastest on rows of at most 128 keys;
# benchmarks/grid_neighbors.py).
DENSE_MAX_AGENTS = 128

# The blocks are at least ``floor(radius)`` cells wide, and wider where agents are spread out so far
# that there would be more than this many blocks per agent (keeps memory linear in n_agents).
BLOCKS_PER_AGENT = 4

INT16_MAX = int(np.iinfo(np.int16).max)
INT32_MAX = int(np.iinfo(np.int32).max)


def grid_neighbors(
    cells: np.ndarray, radius: float, max_neighbors: int, metric: str = "chebyshev"
) -> np.ndarray:
    """Neighbour lists of agents standing on integer grid cells.

    Args:
        cells: ``(n_agents, 2)`` integer cell coordinates; several agents may share a cell.
        radius: communication range, in cells. ``"chebyshev"`` links agents with
            ``max(|dx|, |dy|) <= radius``, ``"euclidean"`` those with ``sqrt(dx**2 + dy**2) <= radius``.
        max_neighbors: width of each row, self included (at least 1).
        metric: ``"chebyshev"`` or ``"euclidean"``.

    Returns:
        ``(n_agents, max_neighbors)`` int64: row ``i`` starts with ``i``, followed by every other agent
        in range (agents sharing ``i``'s cell included) ordered by distance, ties by lower index,
        truncated to ``max_neighbors`` entries; unused entries are ``-1``.

    Cost is linear in ``n_agents`` at a fixed density of agents per cell; no ``n_agents x n_agents``
    array is built above :data:`DENSE_MAX_AGENTS` agents.
    """
    cells = np.asarray(cells)
    if cells.ndim != 2 or cells.shape[1] != 2 or cells.dtype.kind not in "iu":
        raise ValueError(
            f"cells must be an integer array of shape (n_agents, 2), got {cells.dtype} {cells.shape}."
        )
    if metric not in METRICS:
        raise ValueError(f"metric must be one of {METRICS}, got {metric!r}.")
    if not radius >= 0:
        raise ValueError(f"radius must be >= 0, got {radius}.")
    if max_neighbors < 1:
        raise ValueError(f"max_neighbors must be >= 1, got {max_neighbors}.")
    max_key = math.floor(radius) if metric == "chebyshev" else math.floor(radius * radius)
    if len(cells) == 0:
        return np.empty((0, max_neighbors), dtype=np.int64)
    lowest = int(cells.min())
    span = int(cells.max()) - lowest
    if len(cells) <= DENSE_MAX_AGENTS and _fits_dense_keys(len(cells), span, max_key, metric):
        return _dense_neighbors(cells, lowest, max_key, max_neighbors, metric)
    return _blocked_neighbors(cells.astype(np.int64), max_key, max_neighbors, metric)


def living_neighbors(graph: np.ndarray, alive: np.ndarray) -> np.ndarray:
    """Neighbour lists ``(n_agents, max_neighbors)`` int32 of the living agents only: every entry
    naming a gone agent becomes ``-1`` and a gone agent's own list is all ``-1``, so it sends and
    receives no messages. ``graph``: valid lists in ``[-1, n_agents - 1]``; ``alive``: ``(n_agents,)``
    bool."""
    listed = np.append(alive, False)[graph]  # entry -1 reads the appended False
    return np.where(listed & alive[:, None], graph, -1).astype(np.int32)


def subgraph(graph: np.ndarray, members: np.ndarray) -> np.ndarray:
    """The neighbour lists of the agents ``members`` among themselves.

    Args:
        graph: ``(n_agents, max_neighbors)`` valid lists in ``[-1, n_agents - 1]``.
        members: ``(n_members,)`` distinct agent indices.

    Returns:
        ``(n_members, max_neighbors)`` int64: row ``j`` is the list of agent ``members[j]`` with every
        entry renumbered to its position in ``members`` and entries naming other agents ``-1`` (in
        place: the ``-1`` may stand between neighbours, as a list is a set).
    """
    position = np.full(len(graph) + 1, -1, dtype=np.int64)  # entry -1 reads the last one, -1
    position[members] = np.arange(len(members))
    return position[graph[members]]


def _distance_keys(dx: np.ndarray, dy: np.ndarray, max_key: int, metric: str) -> np.ndarray:
    """Distance keys ``max(|dx|, |dy|)`` or ``dx**2 + dy**2`` of the offsets ``(dx, dy)`` (equal shapes).

    A pair is in range iff its key is at most ``max_key``. For Euclidean keys the offsets are first
    clipped per axis to ``isqrt(max_key) + 1``, which keeps every out-of-range key out of range and
    bounds the keys (see :func:`_largest_key`), so small integer dtypes do not overflow.
    """
    dx, dy = np.abs(dx), np.abs(dy)
    if metric == "chebyshev":
        return np.maximum(dx, dy)
    axis_cap = math.isqrt(max_key) + 1
    np.minimum(dx, axis_cap, out=dx)
    np.minimum(dy, axis_cap, out=dy)
    return dx * dx + dy * dy


def _largest_key(span: int, max_key: int, metric: str) -> int:
    """Bound of :func:`_distance_keys` for coordinates that differ by at most ``span`` per axis."""
    if metric == "chebyshev":
        return span
    return 2 * min(math.isqrt(max_key) + 1, span) ** 2


def _index_bits(n_agents: int) -> int:
    """Bits that hold an agent index ``0..n_agents - 1``."""
    return max(1, (n_agents - 1).bit_length())


def _fits_dense_keys(n_agents: int, span: int, max_key: int, metric: str) -> bool:
    """Whether the coordinates and packed keys of :func:`_dense_neighbors` fit in int32."""
    largest_packed_key = (_largest_key(span, max_key, metric) + 2) << _index_bits(n_agents)
    return max(span, largest_packed_key) <= INT32_MAX


def _dense_neighbors(
    cells: np.ndarray, lowest: int, max_key: int, max_neighbors: int, metric: str
) -> np.ndarray:
    """Neighbour lists from one ``(n_agents, n_agents)`` int32 matrix of sort keys, rows sorted in place.

    ``cells`` ``(n_agents, 2)`` have coordinates ``>= lowest``. Each key packs
    ``rank << index_bits | other`` into int32; ranks above ``max_key + 1`` are out of range. numpy
    sorts 32-bit rows with vector instructions on AVX2 and AVX-512 CPUs alike (100 rows of 100 keys
    on a 2-core AMD EPYC with AVX2: 17 us in int32, 41 us in int64, 180 us in int16, whose vectorised
    sort needs AVX-512).
    """
    n_agents = len(cells)
    index_bits = _index_bits(n_agents)
    coordinates = np.ascontiguousarray((cells - lowest).T, dtype=np.int32)
    offsets = coordinates[:, :, None] - coordinates[:, None, :]
    keys = _distance_keys(offsets[0], offsets[1], max_key, metric)
    keys <<= index_bits
    agent_indices = np.arange(n_agents, dtype=np.int32)
    keys += agent_indices + np.int32(1 << index_bits)
    keys.reshape(-1)[:: n_agents + 1] = agent_indices
    keys.sort(axis=1)
    kept = keys[:, :max_neighbors]
    neighbor_lists = (kept & np.int32((1 << index_bits) - 1)).astype(np.int64)
    neighbor_lists[kept >= min((max_key + 2) << index_bits, INT32_MAX)] = -1
    if max_neighbors > n_agents:
        neighbor_lists = np.pad(neighbor_lists, ((0, 0), (0, max_neighbors - n_agents)), constant_values=-1)
    return neighbor_lists


def _blocked_neighbors(cells: np.ndarray, max_key: int, max_neighbors: int, metric: str) -> np.ndarray:
    """Neighbour lists from candidate pairs in nearby blocks (linear cost), see :func:`grid_neighbors`."""
    offsets = cells - cells.min()
    owners, others = _pairs_in_nearby_blocks(
        offsets, math.isqrt(max_key) if metric == "euclidean" else max_key
    )
    x, y = np.ascontiguousarray(offsets.T)
    distance_keys = _distance_keys(x[others] - x[owners], y[others] - y[owners], max_key, metric)
    in_range = np.flatnonzero(distance_keys <= max_key)
    return _ranked_rows(
        owners[in_range], others[in_range], distance_keys[in_range], len(offsets), max_neighbors
    )


def _pairs_in_nearby_blocks(offsets: np.ndarray, axis_range: int) -> tuple[np.ndarray, np.ndarray]:
    """Candidate pairs ``(owner, other)``: ``other`` lies in one of the 3 x 3 blocks around ``owner``.

    ``offsets`` ``(n_agents, 2)`` are non-negative cell coordinates and ``axis_range`` the largest
    per-axis offset in range. Blocks are at least ``axis_range`` cells wide, so every agent in range
    lies in those 9 blocks. Agents are sorted by block id (row-major), so the 3 blocks of one block
    row form one contiguous run of the sorted agents: each owner reads 3 runs. Self pairs are
    included. Returns two ``(n_pairs,)`` int64 arrays with owners in ascending order.
    """
    n_agents = len(offsets)
    extent = int(offsets.max()) + 1
    block_side = max(1, axis_range, math.ceil(extent / math.sqrt(BLOCKS_PER_AGENT * n_agents)))
    blocks_per_row = extent // block_side + 3
    blocks = offsets // block_side + 1
    block_ids = blocks[:, 0] * blocks_per_row + blocks[:, 1]
    n_blocks = blocks_per_row * blocks_per_row
    # block_starts[b] is where block b begins among the sorted agents, block_starts[b + 1] where it ends.
    block_starts = np.zeros(n_blocks + 1, dtype=np.int64)
    np.cumsum(np.bincount(block_ids, minlength=n_blocks), out=block_starts[1:])
    # Stable sorting of 16-bit keys is a radix sort, much faster than sorting 64-bit ones.
    sort_keys = block_ids.astype(np.int16) if n_blocks <= INT16_MAX else block_ids
    agents_by_block = np.argsort(sort_keys, kind="stable")

    row_centres = block_ids[:, None] + np.array([-blocks_per_row, 0, blocks_per_row])[None, :]
    run_starts = block_starts[row_centres - 1]
    run_lengths = block_starts[row_centres + 2] - run_starts
    owners = np.repeat(np.arange(n_agents, dtype=np.int64), run_lengths.sum(axis=1))
    run_lengths = run_lengths.ravel()
    positions = np.arange(len(owners), dtype=np.int64) + np.repeat(
        run_starts.ravel() - (np.cumsum(run_lengths) - run_lengths), run_lengths
    )
    return owners, agents_by_block[positions]


def _ranked_rows(
    owners: np.ndarray,
    others: np.ndarray,
    distance_keys: np.ndarray,
    n_agents: int,
    max_neighbors: int,
) -> np.ndarray:
    """Pack in-range pairs ``(n_pairs,)`` with ascending ``owners`` into ``(n_agents, max_neighbors)``.

    One stable sort of ``(owner, rank, other)`` keys, packed into bit fields, orders every row at
    once; it is fast because the keys already come grouped by owner.
    """
    ranks = distance_keys + (owners != others)
    index_bits = _index_bits(n_agents)
    keys = np.sort(((owners * (int(ranks.max()) + 1) + ranks) << index_bits) | others, kind="stable")
    pairs_per_owner = np.bincount(owners, minlength=n_agents)
    columns = np.arange(len(owners), dtype=np.int64) - (np.cumsum(pairs_per_owner) - pairs_per_owner)[owners]
    # Pairs beyond max_neighbors all land in one spare column, dropped at the end.
    padded_width = max_neighbors + 1
    neighbor_lists = np.full((n_agents, padded_width), -1, dtype=np.int64)
    neighbor_lists.reshape(-1)[owners * padded_width + np.minimum(columns, max_neighbors)] = keys & (
        (1 << index_bits) - 1
    )
    return np.ascontiguousarray(neighbor_lists[:, :max_neighbors])
