"""Sparse attention over neighbour lists: the graphs of a batch prepared once (:class:`GraphBatch`)
and the attention kernel (:func:`neighbor_attention`) the communication layers of
:mod:`sb3_hgrn.common.hgrn` run on.

Agents of ``batch`` independent graphs are processed together. The graph of each batch entry is a
neighbour list ``neighbors`` of shape ``(batch, n_agents, max_neighbors)`` holding agent indices
within the same graph, ``-1`` marking an empty entry. An agent always attends over itself (the
self-loop), so lists may or may not contain ``i`` in row ``i``. A list is a set: an agent listed
several times is one neighbour (only its first entry takes part).

Attention is computed only over the listed neighbours, as sparse (CSR) matrix products over a
pattern of ``max_neighbors + 1`` entries per agent and head: the cost is
``O(batch * n_agents * (max_neighbors + 1))`` per feature; no ``n_agents x n_agents`` matrix is ever
formed.
"""

from __future__ import annotations

import functools
import math
import warnings

import torch
from torch import Tensor


def check_neighbors(neighbors: Tensor, n_agents: int) -> None:
    """Raise a ``ValueError`` unless ``neighbors`` is ``(batch, n_agents, K)`` integer indices in
    ``[-1, n_agents - 1]``.

    Shape and dtype are always checked. The values are checked only on the CPU, where reading them
    costs no device synchronisation; on an accelerator, check the lists where they enter (their CPU
    copy from the env or the replay buffer). :func:`neighbor_entries` treats any index outside
    ``[0, n_agents - 1]`` as an empty entry, so unchecked values never reach another graph.
    """
    if neighbors.dim() != 3 or neighbors.shape[1] != n_agents:
        raise ValueError(
            f"neighbors must have shape (batch, {n_agents}, max_neighbors), got {tuple(neighbors.shape)}"
        )
    if neighbors.dtype.is_floating_point or neighbors.dtype.is_complex or neighbors.dtype == torch.bool:
        raise ValueError(f"neighbors must be an integer tensor, got dtype {neighbors.dtype}")
    if neighbors.device.type == "cpu" and neighbors.numel() > 0:
        low, high = int(neighbors.min()), int(neighbors.max())
        if low < -1 or high >= n_agents:
            raise ValueError(
                f"neighbor indices must lie in [-1, {n_agents - 1}], got values in [{low}, {high}]"
            )


def neighbor_entries(neighbors: Tensor, n_agents: int) -> tuple[Tensor, Tensor, Tensor]:
    """The attention entries of neighbour lists in canonical order, without reading values on the host.

    An agent attends over itself and the distinct agents of its list: a list is a set, an agent
    listed several times is attended once (its first entry) and an entry naming the agent itself
    repeats the self-loop. Rows are the agents of the flattened ``(rows = batch * n_agents, ...)``
    tensors; an entry's target is the flat row ``b * n_agents + j`` of the agent it attends to. The
    entries that take no part (empty, out of range, repeated) each point at a row of their own that
    no entry of the row attends to: with several graphs the row ``b' * n_agents + e`` of the next
    graph ``b' = (b + 1) % batch`` (``e`` the entry's place in the row), with one graph a dummy
    target ``rows + e`` past every agent (operands then get zero rows, see :func:`_padded`). The
    entries of a row come sorted by target and free of repeats, as CSR column indices must be. Lists
    wider than the graph are cut to ``n_agents`` entries, which hold every attended agent.

    :param neighbors: ``(batch, n_agents, max_neighbors)`` integer agent indices, ``-1`` = no entry.
    :param n_agents: number of agents per graph.
    :return: ``targets`` ``(rows, E)`` with ``E = min(max_neighbors + 1, n_agents)``, ``positions``
        ``(rows, E)``: the list place every entry comes from (0 = the agent itself, ``1 + m`` = list
        entry ``m``), distinct in a row, and ``mask`` ``(rows, E)``: True at the entries taking part.
    """
    batch, _, width = neighbors.shape
    rows = batch * n_agents
    device = neighbors.device
    own = torch.arange(n_agents, device=device).view(1, n_agents, 1).expand(batch, n_agents, 1)
    local = torch.cat([own, neighbors.to(torch.long)], dim=2)
    offsets = (torch.arange(batch, device=device) * n_agents).view(batch, 1, 1)
    listed = (local >= 0) & (local < n_agents)
    keys = torch.where(listed, local + offsets, rows).reshape(rows, width + 1)
    # Stable: of equal targets the first list place (the self-loop before a listed self) comes first.
    keys, positions = keys.sort(dim=1, stable=True)
    taken = keys < rows
    taken[:, 1:] &= keys[:, 1:] != keys[:, :-1]
    places = torch.arange(width + 1, device=device)
    keys, moved = torch.where(taken, keys, rows + places).sort(dim=1)
    n_entries = min(width + 1, max(n_agents, 1))
    keys, positions = keys[:, :n_entries], positions.gather(1, moved[:, :n_entries])
    mask = keys < rows
    if batch == 1:
        return torch.where(mask, keys, rows + places[:n_entries]), positions, mask
    next_graph = (torch.arange(rows, device=device) // n_agents + 1) % batch * n_agents
    targets, order = torch.where(mask, keys, next_graph.unsqueeze(1) + places[:n_entries]).sort(dim=1)
    return targets, positions.gather(1, order), mask.gather(1, order)


class _Pattern:
    """Sparsity pattern of the attention of one neighbour structure as CSR index tensors.

    Rows are ``(agent, head)`` pairs ``r * heads + h``, columns ``(target, head)`` pairs
    ``t * heads + h`` over the ``n_targets`` targets of :func:`neighbor_entries` (``rows``, or with
    one graph ``rows + E``: the agents, then the dummy targets): a ``(rows * heads, n_targets *
    heads)`` matrix with exactly ``E`` entries per row, their columns sorted and distinct, so
    ``O(rows * heads * E)`` entries are stored; the values of a matrix on it are laid out as
    ``(rows, heads, E)``. With dummy targets dense right-hand operands get zero rows for them
    (:func:`_padded`). Index tensors are int32 (the type the sparse kernels compute with) unless the
    matrix is too large for it.

    The transposed pattern is needed only for gradients, so it is built on first use, once. Its rows
    come head by head, ``h * n_targets + t`` (a block per head, so no index needs scattering), each
    holding the source rows ``r * heads + h`` of the entries pointing at ``t`` in increasing order:
    ``crow_t`` and ``col_t`` are its CSR index tensors and ``transpose`` maps its values to their
    position in the values of the matrix itself. Acting and target networks, which run without
    gradients, never build it.

    :param targets: ``(rows, E)`` entry targets below ``n_targets`` (see :func:`neighbor_entries`).
    :param heads: attention heads.
    :param n_targets: number of targets.
    :param mask: ``(rows, E)`` True at the entries taking part (see :func:`neighbor_entries`).
    """

    def __init__(self, targets: Tensor, heads: int, n_targets: int, mask: Tensor) -> None:
        rows, n_entries = targets.shape
        self.targets, self.heads, self.n_targets, self.mask = targets, heads, n_targets, mask
        self.shape = (rows * heads, n_targets * heads)
        fits = max(rows * heads * n_entries, *self.shape) < torch.iinfo(torch.int32).max
        self.index_dtype = torch.int32 if fits else torch.long
        self._head = torch.arange(heads, device=targets.device, dtype=self.index_dtype)
        column_of_head = targets.to(self.index_dtype).unsqueeze(1) * heads + self._head.view(1, heads, 1)
        self.col = column_of_head.reshape(-1)
        self.crow = torch.arange(
            0, rows * heads * n_entries + 1, n_entries, device=targets.device, dtype=self.index_dtype
        )

    @functools.cached_property
    def zero_values(self) -> Tensor:
        """Zeros ``(rows * heads * E,)``: the values of the matrix that sampled products fill."""
        return torch.zeros(self.col.numel(), device=self.targets.device)

    @functools.cached_property
    def masked_values(self) -> Tensor:
        """``(rows * heads * E,)``: 0 at the entries taking part, ``-inf`` at the others; sampled
        products added to them are logits masked for the softmax."""
        rows, n_entries = self.mask.shape
        bias = torch.where(self.mask, 0.0, -math.inf)
        return bias.unsqueeze(1).expand(rows, self.heads, n_entries).reshape(-1)

    @functools.cached_property
    def _transposed(self) -> tuple[Tensor, Tensor, Tensor]:
        """``(crow_t, col_t, transpose)``, built once."""
        heads, n_entries, dtype = self.heads, self.targets.shape[1], self.index_dtype
        target = self.targets.reshape(-1).to(dtype)  # entry e = r * E + k points at target[e]
        order = torch.sort(target, stable=True).indices  # by target, then by source row
        counts = torch.zeros(self.n_targets, dtype=torch.long, device=target.device)
        counts.scatter_add_(0, target.long(), torch.ones_like(target, dtype=torch.long))
        ends = counts.cumsum(0)  # entries at targets <= t
        source_row, place = order // n_entries, order % n_entries
        head = self._head.unsqueeze(1)
        # Block h lists the entries in `order` again, with columns and values of head h.
        col_t = (source_row.to(dtype) * heads + head).reshape(-1)
        transpose = ((source_row * heads * n_entries + place).to(dtype) + head * n_entries).reshape(-1)
        crow_t = torch.zeros(heads * self.n_targets + 1, dtype=dtype, device=target.device)
        block_ends = ends.to(dtype) + head * target.numel()
        crow_t[1:] = block_ends.reshape(-1)
        return crow_t, col_t, transpose

    @property
    def crow_t(self) -> Tensor:
        return self._transposed[0]

    @property
    def col_t(self) -> Tensor:
        return self._transposed[1]

    @property
    def transpose(self) -> Tensor:
        return self._transposed[2]


def _sparse(crow: Tensor, col: Tensor, values: Tensor, shape: tuple[int, int]) -> Tensor:
    """CSR matrix of ``shape`` with the given index tensors and flat ``values``.

    The patterns have sorted, distinct columns in every row by construction; they are checked only
    under ``torch.sparse.check_sparse_tensor_invariants()`` (the tests turn it on; checking reads
    the indices on the host).
    """
    check = torch.sparse.check_sparse_tensor_invariants.is_enabled()
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", "Sparse CSR tensor support is in beta state")
        return torch.sparse_csr_tensor(crow, col, values, shape, check_invariants=check)


def _padded(pattern: _Pattern, dense: Tensor) -> Tensor:
    """``dense`` ``(rows * heads, head_dim)`` with zero rows for the dummy targets appended:
    ``((rows + E) * heads, head_dim)``, a right-hand operand of the matrices on ``pattern``; ``dense``
    itself when the pattern has no dummy targets (several graphs)."""
    extra = pattern.shape[1] - pattern.shape[0]
    return dense if extra == 0 else torch.cat([dense, dense.new_zeros(extra, dense.shape[1])])


def _matmul(pattern: _Pattern, values: Tensor, dense: Tensor, transposed: bool = False) -> Tensor:
    """``M @ dense`` (or ``M^T @ dense``) for the matrix ``M`` with ``values`` ``(rows, heads, E)``
    on ``pattern``; ``dense`` is ``((rows + E) * heads, head_dim)`` (see :func:`_padded`), or
    ``(rows * heads, head_dim)`` if ``transposed``. :return: ``(rows * heads, head_dim)``."""
    values = values.reshape(-1)
    rows, columns = pattern.shape
    if not transposed:
        return _sparse(pattern.crow, pattern.col, values, pattern.shape) @ dense
    matrix = _sparse(
        pattern.crow_t, pattern.col_t, values.index_select(0, pattern.transpose), (columns, rows)
    )
    by_head = (matrix @ dense).view(pattern.heads, pattern.n_targets, -1)  # rows h * n_targets + t
    return by_head[:, : rows // pattern.heads].transpose(0, 1).reshape(rows, -1)


def _sampled_dot(pattern: _Pattern, left: Tensor, right: Tensor, masked: bool = False) -> Tensor:
    """Dot products ``left[row] . right[col]`` ``(rows * heads * E,)`` at the entries of ``pattern``
    (``-inf`` at the entries taking no part if ``masked``); ``left`` ``(rows * heads, head_dim)``,
    ``right`` ``((rows + E) * heads, head_dim)`` (see :func:`_padded`)."""
    start = (pattern.masked_values if masked else pattern.zero_values).to(left.dtype)
    return torch.sparse.sampled_addmm(
        _sparse(pattern.crow, pattern.col, start, pattern.shape), left, right.t(), beta=1.0 if masked else 0.0
    ).values()


def _attend(
    query: Tensor, key: Tensor, value: Tensor, pattern: _Pattern, segments: list[Tensor]
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """The attention of :class:`NeighborAttention` without autograd: outputs ``(rows, n_segments,
    heads, head_dim)``, weights ``(rows, heads, E)``, and the scaled queries and padded keys and
    values ``(rows', head_dim)`` its backward pass reads."""
    rows, heads, head_dim = query.shape
    scaled_query = (query * head_dim**-0.5).reshape(-1, head_dim)
    key, value = (_padded(pattern, tensor.reshape(-1, head_dim)) for tensor in (key, value))
    masked = len(segments) == 1 and segments[0] is pattern.mask  # the pattern's own mask: sampled in
    logits = _sampled_dot(pattern, scaled_query, key, masked).view(rows, heads, -1)
    if len(segments) == 1:
        if not masked:
            logits.masked_fill_(~segments[0].unsqueeze(1), -math.inf)
        weights = logits.softmax(dim=-1)
        out = _matmul(pattern, weights, value).view(rows, 1, heads, head_dim)
    else:
        selections = [segment.unsqueeze(1).to(logits.dtype) for segment in segments]
        weights = torch.zeros_like(logits)
        for segment in segments:
            segment_weights = logits.masked_fill(~segment.unsqueeze(1), -math.inf).softmax(dim=-1)
            weights += segment_weights.nan_to_num_(0.0)  # a row without entries in the segment
        outputs = [_matmul(pattern, weights * selection, value) for selection in selections]
        out = torch.stack([output.view(rows, heads, head_dim) for output in outputs], dim=1)
    return out, weights, scaled_query, key, value


def neighbor_attention(
    query: Tensor, key: Tensor, value: Tensor, pattern: _Pattern, segments: list[Tensor]
) -> tuple[Tensor, Tensor]:
    """Masked multi-head attention over neighbour entries (:class:`NeighborAttention`): through the
    autograd function where a gradient is recorded, else the bare computation, which skips the
    function's bookkeeping (a sixth to a quarter of the kernel's time for one graph of 100 agents).

    :return: outputs ``(rows, n_segments, heads, head_dim)`` and weights ``(rows, heads, E)``.
    """
    if torch.is_grad_enabled() and (query.requires_grad or key.requires_grad or value.requires_grad):
        return NeighborAttention.apply(query, key, value, pattern, segments)
    return _attend(query, key, value, pattern, segments)[:2]


class NeighborAttention(torch.autograd.Function):
    """Masked multi-head attention over neighbour entries as sparse (CSR) matrix products.

    Logits are sampled dot products at the ``E`` entries of every row only (:class:`_Pattern`) and
    the weighted sums of values are sparse-dense products, so nothing of size
    ``(rows, E, heads, head_dim)`` is formed; the backward pass uses the transposed pattern for the
    gradients of keys and values. Entries are in the canonical order of :func:`neighbor_entries`.

    Entries may fall into several segments (the sender groups of heterogeneous attention): the
    softmax then runs within each segment of a row separately and each segment gives its own
    output, zero when the row has no entry in it. One segment is ordinary graph attention.
    """

    @staticmethod
    def forward(
        ctx, query: Tensor, key: Tensor, value: Tensor, pattern: _Pattern, segments: list[Tensor]
    ) -> tuple[Tensor, Tensor]:
        """``query``/``key``/``value`` ``(rows, heads, head_dim)``; ``segments``: one bool mask
        ``(rows, E)`` per segment marking its entries (disjoint, never a dummy entry; entries in none
        are masked out). Returns outputs ``(rows, n_segments, heads, head_dim)`` and attention weights
        ``(rows, heads, E)`` (each segment of a row sums to one, or to zero if it is empty)."""
        out, weights, scaled_query, key, value = _attend(query, key, value, pattern, segments)
        ctx.save_for_backward(scaled_query, key, value, weights, *segments)
        ctx.pattern = pattern
        ctx.mark_non_differentiable(weights)
        return out, weights

    @staticmethod
    def backward(ctx, grad_out: Tensor, _grad_weights: Tensor | None) -> tuple[Tensor | None, ...]:
        scaled_query, key, value, weights, *segments = ctx.saved_tensors
        pattern = ctx.pattern
        rows, n_segments, heads, head_dim = grad_out.shape
        grad_weights = torch.zeros_like(weights)  # d loss / d weight of every entry
        weighted_sums = torch.zeros_like(weights)  # per entry: sum over its segment of weight * that
        grad_value = torch.zeros_like(scaled_query)
        for index, segment in enumerate(segments):
            selection = segment.unsqueeze(1).to(weights.dtype) if n_segments > 1 else 1.0
            segment_grad_out = grad_out[:, index].reshape(-1, head_dim)
            segment_weights = weights * selection
            dots = _sampled_dot(pattern, segment_grad_out, value).view(weights.shape) * selection
            grad_weights += dots
            weighted_sums += (segment_weights * dots).sum(dim=-1, keepdim=True) * selection
            grad_value += _matmul(pattern, segment_weights, segment_grad_out, transposed=True)
        grad_logits = weights * (grad_weights - weighted_sums)
        grad_query = _matmul(pattern, grad_logits, key).mul_(head_dim**-0.5)
        grad_key = _matmul(pattern, grad_logits, scaled_query, transposed=True)
        shape = (rows, heads, head_dim)
        return grad_query.view(shape), grad_key.view(shape), grad_value.view(shape), None, None


class RowGroups:
    """The agent groups of a block of rows, as per-group layers read them: ``row_groups`` ``(rows,)``
    the group of every row, ``group_rows`` the rows of each group (increasing; found with
    ``torch.nonzero``, which synchronises with an accelerator) and ``group_inverse`` the place of
    every row in their concatenation.

    :param row_groups: ``(rows,)`` int64 group ids in ``[0, n_groups - 1]``.
    :param n_groups: number of groups.
    """

    def __init__(self, row_groups: Tensor, n_groups: int) -> None:
        self.row_groups = row_groups
        self.group_rows = [torch.nonzero(row_groups == group).squeeze(1) for group in range(n_groups)]
        self.group_inverse = torch.argsort(torch.cat(self.group_rows))


class GraphBatch:
    """A batch of graphs prepared once per forward pass and shared by the communication layers.

    Build it once per batch of graphs and pass it to every network reading them (an actor and its
    critics): the attention patterns are cached per head count, so networks of any head counts can
    share it. With one group, preparing it and attending over it (forward and backward) never read
    values of accelerator tensors on the host, so they never synchronise (neighbour values are
    validated only on the CPU, see :func:`check_neighbors`). With several groups the rows of each
    group are found with ``torch.nonzero`` and the group ids are validated, which synchronises.

    Entries (``E = min(max_neighbors + 1, n_agents)`` per agent, see :func:`neighbor_entries`) are
    held in canonical order: ``targets`` ``(rows, E)`` (``rows = batch * n_agents``), ``positions``
    ``(rows, E)`` their list places, ``mask`` ``(rows, E)`` the entries taking part and ``columns``
    ``(rows, E)`` the flat agent row of every entry (the agent itself where none takes part). They are
    computed on first use, so a network that never reads the neighbours (no communication) never
    pays for them; the neighbours are validated at once.

    :param neighbors: ``(batch, n_agents, max_neighbors)`` agent indices within the same graph,
        ``-1`` = no entry; an agent listed several times is one neighbour.
    :param groups: ``(batch, n_agents)`` group id of every agent (``None``: all in group 0).
    :param n_groups: number of agent groups the network has.
    """

    def __init__(self, neighbors: Tensor, groups: Tensor | None = None, n_groups: int = 1) -> None:
        self.batch, self.n_agents = neighbors.shape[:2]
        self.rows = self.batch * self.n_agents
        self.n_groups = n_groups
        check_neighbors(neighbors, self.n_agents)
        self.neighbors = neighbors
        self.list_width = neighbors.shape[2]
        self._patterns: dict[int, _Pattern] = {}
        self.group_rows: list[Tensor] | None = None
        self.group_inverse: Tensor | None = None
        self.row_groups: Tensor | None = None
        if n_groups > 1:
            self._prepare_groups(groups)

    @functools.cached_property
    def _entries(self) -> tuple[Tensor, Tensor, Tensor]:
        return neighbor_entries(self.neighbors, self.n_agents)

    @property
    def targets(self) -> Tensor:
        return self._entries[0]

    @property
    def positions(self) -> Tensor:
        return self._entries[1]

    @property
    def mask(self) -> Tensor:
        return self._entries[2]

    @property
    def n_targets(self) -> int:
        """Columns of the attention patterns: the agents' rows, with one graph also dummy targets."""
        return self.rows if self.batch > 1 else self.rows + self.targets.shape[1]

    @functools.cached_property
    def columns(self) -> Tensor:
        own = torch.arange(self.rows, device=self.neighbors.device).unsqueeze(1)
        return torch.where(self.mask, self.targets, own)

    @functools.cached_property
    def column_groups(self) -> Tensor | None:
        """``(rows, E)`` the group of every entry (``None`` with one group)."""
        return None if self.row_groups is None else self.row_groups[self.columns]

    def _prepare_groups(self, groups: Tensor | None) -> None:
        if groups is None or tuple(groups.shape) != (self.batch, self.n_agents):
            shape = None if groups is None else tuple(groups.shape)
            raise ValueError(
                f"A network of {self.n_groups} agent groups needs groups of shape "
                f"{(self.batch, self.n_agents)}, got {shape}."
            )
        flat = groups.reshape(-1).long()
        if flat.numel() and (int(flat.min()) < 0 or int(flat.max()) >= self.n_groups):
            raise ValueError(f"group ids must lie in [0, {self.n_groups - 1}].")
        groups = RowGroups(flat, self.n_groups)
        self.row_groups, self.group_rows, self.group_inverse = flat, groups.group_rows, groups.group_inverse

    def block(self, first_graph: int, n_graphs: int) -> RowGroups | None:
        """The agent groups of the rows of graphs ``first_graph`` to ``first_graph + n_graphs - 1``
        (``None`` with one group), for per-group layers run on those rows alone."""
        if self.row_groups is None:
            return None
        start = first_graph * self.n_agents
        return RowGroups(self.row_groups[start : start + n_graphs * self.n_agents], self.n_groups)

    def list_weights(self, weights: Tensor) -> Tensor:
        """Attention weights ``(rows, heads, E)`` in canonical order laid out over the lists:
        ``(rows, heads, list_width + 1)``, column 0 the agent itself, ``1 + m`` list entry ``m``, zero
        at the entries taking no part."""
        positions = self.positions.unsqueeze(1).expand(-1, weights.shape[1], -1)
        return weights.new_zeros(*weights.shape[:2], self.list_width + 1).scatter_(2, positions, weights)

    def pattern(self, heads: int) -> _Pattern:
        """CSR pattern of the attention with ``heads`` heads (built once per head count)."""
        if heads not in self._patterns:
            self._patterns[heads] = _Pattern(self.targets, heads, self.n_targets, self.mask)
        return self._patterns[heads]

    def segments(self, across_groups: bool) -> list[Tensor]:
        """Bool masks ``(rows, E)`` of the entries attended together: one per sender group
        (``across_groups``), or a single one over the neighbours of the agent's own group."""
        if self.n_groups == 1:
            return [self.mask]
        if across_groups:
            return [self.mask & (self.column_groups == group) for group in range(self.n_groups)]
        return [self.mask & (self.column_groups == self.row_groups.unsqueeze(1))]


def as_graph_batch(graph: GraphBatch | Tensor) -> GraphBatch:
    return graph if isinstance(graph, GraphBatch) else GraphBatch(graph)
