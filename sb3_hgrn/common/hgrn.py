"""HGRN: graph-recurrent network over neighbour lists (pure torch).

Agents of ``batch`` independent graphs are processed together. The graph of each batch entry is a
neighbour list ``neighbors`` of shape ``(batch, n_agents, max_neighbors)`` holding agent indices
within the same graph, ``-1`` marking an empty entry. Every communication layer always adds the
agent itself (the self-loop), so lists may or may not contain ``i`` in row ``i``.

Attention is computed only over the listed neighbours: keys and values are gathered by index and
the cost is ``O(batch * n_agents * (max_neighbors + 1))``; no ``n_agents x n_agents`` matrix is
ever formed.
"""

from __future__ import annotations

import contextlib
import math
import warnings
from collections.abc import Callable, Sequence
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn

PAPER_SIZE: dict = {"hidden_dim": 256, "n_heads": 4, "head_dim": 256}
"""Network size of the original HGRN (4 heads of width 256 on a hidden size of 256)."""

COMMUNICATIONS = ("hgat", "gat", "mean", "none")

MASKED_OUTPUT = -1e9
"""Output of the actions an agent's group does not have: softmax gives them probability 0."""


def check_neighbors(neighbors: Tensor, n_agents: int) -> None:
    """Raise a ``ValueError`` unless ``neighbors`` is ``(batch, n_agents, K)`` integer indices in
    ``[-1, n_agents - 1]``."""
    if neighbors.dim() != 3 or neighbors.shape[1] != n_agents:
        raise ValueError(
            f"neighbors must have shape (batch, {n_agents}, max_neighbors), got {tuple(neighbors.shape)}"
        )
    if neighbors.dtype.is_floating_point or neighbors.dtype.is_complex or neighbors.dtype == torch.bool:
        raise ValueError(f"neighbors must be an integer tensor, got dtype {neighbors.dtype}")
    if neighbors.numel() > 0:
        low, high = int(neighbors.min()), int(neighbors.max())
        if low < -1 or high >= n_agents:
            raise ValueError(
                f"neighbor indices must lie in [-1, {n_agents - 1}], got values in [{low}, {high}]"
            )


def neighbor_columns(neighbors: Tensor, n_agents: int) -> tuple[Tensor, Tensor]:
    """Turn checked neighbour lists (see :func:`check_neighbors`) into flat gather indices with the
    self-loop in column 0.

    :param neighbors: ``(batch, n_agents, max_neighbors)`` integer agent indices, ``-1`` = no entry.
    :param n_agents: number of agents per graph.
    :return: ``columns`` of shape ``(max_neighbors + 1, batch * n_agents)`` with flat row indices
        ``b * n_agents + j`` into a ``(batch * n_agents, ...)`` tensor (entries that are empty or
        equal to the agent itself point at the agent and are masked), and ``mask`` of shape
        ``(batch * n_agents, max_neighbors + 1)``, True for the entries that take part (column 0,
        the agent itself, is always True).
    """
    batch = neighbors.shape[0]
    neighbors = neighbors.to(torch.long)
    own = torch.arange(n_agents, device=neighbors.device).view(1, n_agents, 1).expand(batch, n_agents, 1)
    valid = (neighbors >= 0) & (neighbors != own)
    local = torch.cat([own, torch.where(valid, neighbors, own)], dim=2)
    offsets = (torch.arange(batch, device=neighbors.device) * n_agents).view(batch, 1, 1)
    columns = (local + offsets).reshape(batch * n_agents, -1).t().contiguous()
    itself = torch.ones(batch, n_agents, 1, dtype=torch.bool, device=neighbors.device)
    mask = torch.cat([itself, valid], dim=2).reshape(batch * n_agents, -1)
    return columns, mask


class _Pattern(NamedTuple):
    """Sparsity pattern of the attention of one neighbour structure as CSR index tensors.

    Rows and columns are ``(agent, head)`` pairs ``r * heads + h`` of a ``(rows * heads, rows * heads)``
    matrix with exactly ``K + 1`` entries per row (the listed columns of ``neighbor_columns``), so
    ``O(rows * heads * (K + 1))`` entries are stored. ``transpose`` maps the values of the transposed
    matrix (same pattern, rows sorted) to their position in the values of the matrix itself.
    """

    crow: Tensor
    col: Tensor
    crow_t: Tensor
    col_t: Tensor
    transpose: Tensor
    size: int


def _attention_pattern(columns: Tensor, heads: int) -> _Pattern:
    """Build the CSR pattern of attention over ``columns`` ``(K + 1, rows)`` for ``heads`` heads; the
    values of a matrix on it are laid out as ``(rows, heads, K + 1)``."""
    n_columns, rows = columns.shape
    device = columns.device
    head = torch.arange(heads, device=device)
    target = columns.t().reshape(-1)  # entry e = r * (K + 1) + c points at agent target[e]
    col = (target.view(rows, 1, n_columns) * heads + head.view(1, heads, 1)).reshape(-1)
    crow = torch.arange(0, rows * heads * n_columns + 1, n_columns, device=device)
    order = torch.argsort(target, stable=True)
    count = torch.bincount(target, minlength=rows)
    first = torch.cumsum(count, 0) - count
    sorted_target = target[order]
    # Transposed row (j, h) holds the count[j] entries pointing at j, in the order of ``order``.
    dest = ((heads - 1) * first[sorted_target] + torch.arange(order.numel(), device=device)).unsqueeze(
        1
    ) + head * count[sorted_target].unsqueeze(1)
    source_row = (order // n_columns * heads).unsqueeze(1) + head
    transpose = torch.empty(dest.numel(), dtype=torch.long, device=device)
    transpose[dest.reshape(-1)] = (source_row * n_columns + (order % n_columns).unsqueeze(1)).reshape(-1)
    col_t = torch.empty_like(transpose)
    col_t[dest.reshape(-1)] = source_row.reshape(-1)
    crow_t = torch.zeros(rows * heads + 1, dtype=torch.long, device=device)
    torch.cumsum(count.repeat_interleave(heads), 0, out=crow_t[1:])
    return _Pattern(crow, col, crow_t, col_t, transpose, rows * heads)


def _sparse(crow: Tensor, col: Tensor, values: Tensor, size: int) -> Tensor:
    """``(size, size)`` CSR matrix with the given index tensors and flat ``values``."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", "Sparse CSR tensor support is in beta state")
        return torch.sparse_csr_tensor(crow, col, values, (size, size), check_invariants=False)


def _matmul(pattern: _Pattern, values: Tensor, dense: Tensor, transposed: bool = False) -> Tensor:
    """``M @ dense`` (or ``M^T @ dense``) for the matrix ``M`` with ``values`` ``(rows, heads, K + 1)``
    on ``pattern``; ``dense`` ``(rows * heads, head_dim)``."""
    values = values.reshape(-1)
    if transposed:
        return _sparse(pattern.crow_t, pattern.col_t, values[pattern.transpose], pattern.size) @ dense
    return _sparse(pattern.crow, pattern.col, values, pattern.size) @ dense


def _sampled_dot(pattern: _Pattern, left: Tensor, right: Tensor) -> Tensor:
    """Dot products ``left[row] . right[col]`` ``(rows * heads * (K + 1),)`` at the entries of
    ``pattern``; ``left``, ``right`` ``(rows * heads, head_dim)``."""
    zeros = torch.zeros(pattern.col.numel(), dtype=left.dtype, device=left.device)
    return torch.sparse.sampled_addmm(
        _sparse(pattern.crow, pattern.col, zeros, pattern.size), left, right.t(), beta=0.0
    ).values()


class _NeighborAttention(torch.autograd.Function):
    """Masked multi-head attention over gathered neighbours as sparse (CSR) matrix products.

    Logits are sampled dot products at the listed entries only and the weighted sums of values are
    sparse-dense products, so nothing of size ``(rows, K + 1, heads, head_dim)`` is formed; the
    backward pass uses the transposed pattern for the gradients of keys and values.

    Entries may fall into several segments (the sender groups of heterogeneous attention): the
    softmax then runs within each segment of a row separately and each segment gives its own
    output, zero when the row has no entry in it. One segment is ordinary graph attention.
    """

    @staticmethod
    def forward(
        ctx, query: Tensor, key: Tensor, value: Tensor, pattern: _Pattern, segments: list[Tensor]
    ) -> tuple[Tensor, Tensor]:
        """``query``/``key``/``value`` ``(rows, heads, head_dim)``; ``segments``: one bool mask
        ``(rows, K + 1)`` per segment marking its entries (disjoint; entries in none are masked out).
        Returns outputs ``(rows, n_segments, heads, head_dim)`` and attention weights
        ``(rows, heads, K + 1)`` (each segment of a row sums to one, or to zero if it is empty)."""
        rows, heads, head_dim = query.shape
        scaled_query = (query * head_dim**-0.5).reshape(-1, head_dim)
        key, value = key.reshape(-1, head_dim), value.reshape(-1, head_dim)
        logits = _sampled_dot(pattern, scaled_query, key).view(rows, heads, -1)
        if len(segments) == 1:
            weights = logits.masked_fill_(~segments[0].unsqueeze(1), -math.inf).softmax(dim=-1)
            outputs = [_matmul(pattern, weights, value)]
        else:
            selections = [segment.unsqueeze(1).to(logits.dtype) for segment in segments]
            weights = torch.zeros_like(logits)
            for segment in segments:
                segment_weights = logits.masked_fill(~segment.unsqueeze(1), -math.inf).softmax(dim=-1)
                weights += segment_weights.nan_to_num_(0.0)  # a row without entries in the segment
            outputs = [_matmul(pattern, weights * selection, value) for selection in selections]
        out = torch.stack([output.view(rows, heads, head_dim) for output in outputs], dim=1)
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
        grad_value = torch.zeros_like(value)
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


def _check_positive(**sizes: int) -> None:
    for name, size in sizes.items():
        if size <= 0:
            raise ValueError(f"{name} must be positive, got {size}")


class GraphBatch:
    """A batch of graphs prepared once per forward pass and shared by the communication layers.

    :param neighbors: ``(batch, n_agents, max_neighbors)`` agent indices within the same graph,
        ``-1`` = no entry.
    :param groups: ``(batch, n_agents)`` group id of every agent (``None``: all in group 0).
    :param n_groups: number of agent groups the network has.
    """

    def __init__(self, neighbors: Tensor, groups: Tensor | None = None, n_groups: int = 1) -> None:
        self.batch, self.n_agents = neighbors.shape[:2]
        self.n_groups = n_groups
        check_neighbors(neighbors, self.n_agents)
        self.list_width = neighbors.shape[2]
        self.kept_entries: Tensor | None = None
        if self.list_width >= max(self.n_agents, 1):
            neighbors, self.kept_entries = _compact_lists(neighbors, self.n_agents)
        self.columns, self.mask = neighbor_columns(neighbors, self.n_agents)
        self._patterns: dict[int, _Pattern] = {}
        self.group_rows: list[Tensor] | None = None
        self.group_inverse: Tensor | None = None
        self.row_groups: Tensor | None = None
        self.column_groups: Tensor | None = None
        if n_groups > 1:
            self._prepare_groups(groups)

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
        self.row_groups = flat
        self.group_rows = [torch.nonzero(flat == group).squeeze(1) for group in range(self.n_groups)]
        self.group_inverse = torch.argsort(torch.cat(self.group_rows))
        self.column_groups = flat[self.columns.t()]  # (rows, K + 1) group of every listed entry

    def list_weights(self, weights: Tensor) -> Tensor:
        """Attention weights ``(batch * n_agents, heads, K' + 1)`` over the (possibly compacted) lists,
        laid out over the original lists ``(batch * n_agents, heads, list_width + 1)``."""
        if self.kept_entries is None:
            return weights
        full = weights.new_zeros(*weights.shape[:2], self.list_width + 1)
        full[..., 0] = weights[..., 0]
        positions = (self.kept_entries.reshape(weights.shape[0], 1, -1) + 1).expand(-1, weights.shape[1], -1)
        return full.scatter_(2, positions, weights[..., 1:])

    def pattern(self, heads: int) -> _Pattern:
        """CSR pattern of the attention with ``heads`` heads (built once per head count)."""
        if heads not in self._patterns:
            self._patterns[heads] = _attention_pattern(self.columns, heads)
        return self._patterns[heads]

    def segments(self, across_groups: bool) -> list[Tensor]:
        """Bool masks ``(rows, K + 1)`` of the entries attended together: one per sender group
        (``across_groups``), or a single one over the neighbours of the agent's own group."""
        if self.n_groups == 1:
            return [self.mask]
        if across_groups:
            return [self.mask & (self.column_groups == group) for group in range(self.n_groups)]
        return [self.mask & (self.column_groups == self.row_groups.unsqueeze(1))]


def _compact_lists(neighbors: Tensor, n_agents: int) -> tuple[Tensor, Tensor]:
    """Shorten lists with at least ``n_agents`` entries to ``n_agents - 1``, valid entries first.

    No agent has more than ``n_agents - 1`` others, so only empty entries, entries naming the agent
    itself and repeated entries can fall off (a repeated neighbour then counts fewer times). The
    sparse attention needs this: it cannot hold more entries per row than the graph has agents.
    :return: the shortened lists and the positions ``(batch, n_agents, n_agents - 1)`` they came from.
    """
    own = torch.arange(n_agents, device=neighbors.device).view(1, n_agents, 1)
    invalid = ((neighbors < 0) | (neighbors == own)).to(torch.int8)
    kept = torch.argsort(invalid, dim=2, stable=True)[..., : n_agents - 1]
    return neighbors.gather(2, kept), kept


def _as_graph(graph: GraphBatch | Tensor) -> GraphBatch:
    return graph if isinstance(graph, GraphBatch) else GraphBatch(graph)


class Grouped(nn.Module):
    """One copy of a module per agent group: every row goes through its agent's group's copy.

    :param make: builds one copy.
    :param n_groups: number of groups.
    """

    def __init__(self, make: Callable[[], nn.Module], n_groups: int = 1) -> None:
        super().__init__()
        _check_positive(n_groups=n_groups)
        self.members = nn.ModuleList(make() for _ in range(n_groups))

    def __getitem__(self, group: int) -> nn.Module:
        return self.members[group]

    def forward(self, *inputs: Tensor, graph: GraphBatch | None = None) -> Tensor:
        """Apply the copies to ``inputs`` whose leading dimensions are the agents of ``graph``
        (``(batch, n_agents, ...)`` or flattened ``(batch * n_agents, ...)``); one group needs no graph."""
        if len(self.members) == 1:
            return self.members[0](*inputs)
        leading = inputs[0].shape[:-1]
        flat = [x.reshape(-1, x.shape[-1]) for x in inputs]
        outputs = [
            member(*(x.index_select(0, rows) for x in flat))
            for member, rows in zip(self.members, graph.group_rows, strict=True)
        ]
        out = torch.cat(outputs).index_select(0, graph.group_inverse)
        return out.reshape(*leading, out.shape[-1])


class GraphAttention(nn.Module):
    """Multi-head (heterogeneous) graph attention over neighbour lists, self-loop always included.

    ``q, k, v = ReLU(Linear(x))`` with ``n_heads * head_dim`` features each; agent ``i`` attends over
    itself and its valid listed neighbours with logits ``q_i . k_j / sqrt(head_dim)``; heads are
    concatenated and mapped by ``ReLU(Linear(n_heads * head_dim -> out_dim))``.

    With several agent groups (HGAT) the receiver's group owns the query and the output map, the
    sender's group owns the key and value; ``across_groups=True`` attends over the neighbours of each
    sender group separately, giving one message per group (zero if the agent has no neighbour of that
    group), and maps the concatenated messages ``(n_groups * n_heads * head_dim)`` to ``out_dim``;
    ``across_groups=False`` attends only over neighbours of the agent's own group. With one group
    both are plain graph attention.

    :param in_dim: input features per agent.
    :param out_dim: output features per agent.
    :param n_heads: number of attention heads.
    :param head_dim: features per head.
    :param n_groups: number of agent groups.
    :param across_groups: attend over every sender group (HGAT) or within the own group only.
    """

    def __init__(
        self,
        in_dim: int,
        out_dim: int,
        n_heads: int,
        head_dim: int,
        n_groups: int = 1,
        across_groups: bool = True,
    ) -> None:
        super().__init__()
        _check_positive(in_dim=in_dim, out_dim=out_dim, n_heads=n_heads, head_dim=head_dim)
        self.n_heads = n_heads
        self.head_dim = head_dim
        self.across_groups = across_groups
        width = n_heads * head_dim
        messages = n_groups if across_groups else 1
        self.query = Grouped(lambda: nn.Linear(in_dim, width), n_groups)
        self.key = Grouped(lambda: nn.Linear(in_dim, width), n_groups)
        self.value = Grouped(lambda: nn.Linear(in_dim, width), n_groups)
        self.output = Grouped(lambda: nn.Linear(messages * width, out_dim), n_groups)

    def project(self, x: Tensor, graph: GraphBatch) -> tuple[Tensor, Tensor, Tensor]:
        """Queries, keys and values ``(batch * n_agents, n_heads, head_dim)`` of ``x``
        ``(batch, n_agents, in_dim)``."""
        shape = (-1, self.n_heads, self.head_dim)
        return tuple(
            F.relu(layer(x, graph=graph)).reshape(shape) for layer in (self.query, self.key, self.value)
        )

    def forward(
        self, x: Tensor, graph: GraphBatch | Tensor, return_attention: bool = False
    ) -> Tensor | tuple[Tensor, Tensor]:
        """Attend over neighbours.

        :param x: ``(batch, n_agents, in_dim)`` agent features.
        :param graph: the prepared :class:`GraphBatch`, or neighbour lists ``(batch, n_agents,
            max_neighbors)`` (agent indices within the same graph, ``-1`` = no entry) of one group.
        :param return_attention: also return the attention weights.
        :return: ``(batch, n_agents, out_dim)``; with ``return_attention`` also the weights
            ``(batch, n_agents, n_heads, max_neighbors + 1)``, column 0 being the agent itself and
            column ``1 + m`` the list entry ``m`` (zero where the entry is empty, the agent itself, or
            not attended); with several sender groups the weights of each group sum to one.
        """
        graph = _as_graph(graph)
        batch, n_agents, _ = x.shape
        query, key, value = self.project(x, graph)
        segments = graph.segments(self.across_groups)
        dtype = torch.promote_types(query.dtype, torch.float32)  # bfloat16 under autocast -> float32
        with torch.autocast(x.device.type, enabled=False):  # the sparse kernels run in full precision
            mixed, weights = _NeighborAttention.apply(
                query.to(dtype), key.to(dtype), value.to(dtype), graph.pattern(self.n_heads), segments
            )
        out = F.relu(self.output(mixed.reshape(batch, n_agents, -1), graph=graph))
        if return_attention:
            return out, graph.list_weights(weights).reshape(batch, n_agents, self.n_heads, -1)
        return out


class MeanCommunication(nn.Module):
    """CommNet-style communication: ``ReLU(Linear([x_i, mean_j x_j]))`` over valid neighbours ``j != i``.

    The mean is zero for an agent without neighbours. With several groups, each receiver group has
    its own output map.

    :param in_dim: input features per agent.
    :param out_dim: output features per agent.
    :param n_groups: number of agent groups.
    """

    def __init__(self, in_dim: int, out_dim: int, n_groups: int = 1) -> None:
        super().__init__()
        _check_positive(in_dim=in_dim, out_dim=out_dim)
        self.output = Grouped(lambda: nn.Linear(2 * in_dim, out_dim), n_groups)

    def forward(self, x: Tensor, graph: GraphBatch | Tensor) -> Tensor:
        """:param x: ``(batch, n_agents, in_dim)``; :param graph: :class:`GraphBatch` or neighbour
        lists ``(batch, n_agents, max_neighbors)``. :return: ``(batch, n_agents, out_dim)``."""
        graph = _as_graph(graph)
        batch, n_agents, in_dim = x.shape
        others = graph.mask[:, 1:].t().unsqueeze(-1).to(x.dtype)  # (K, rows, 1)
        gathered = x.reshape(-1, in_dim).index_select(0, graph.columns[1:].reshape(-1))
        total = (gathered.reshape(*others.shape[:2], in_dim) * others).sum(0)
        mean = total / others.sum(0).clamp(min=1.0)
        joined = torch.cat([x, mean.reshape(batch, n_agents, in_dim)], dim=-1)
        return F.relu(self.output(joined, graph=graph))


class SelfOnly(nn.Module):
    """No communication (the "-G" ablation): attention over the agent alone.

    Equals :class:`GraphAttention` with an empty graph: ``ReLU(Linear(ReLU(Linear(x))))`` through
    ``n_heads * head_dim`` value features (per group with several groups).

    :param in_dim: input features per agent.
    :param out_dim: output features per agent.
    :param n_heads: number of (value) heads.
    :param head_dim: features per head.
    :param n_groups: number of agent groups.
    """

    def __init__(self, in_dim: int, out_dim: int, n_heads: int, head_dim: int, n_groups: int = 1) -> None:
        super().__init__()
        _check_positive(in_dim=in_dim, out_dim=out_dim, n_heads=n_heads, head_dim=head_dim)
        self.value = Grouped(lambda: nn.Linear(in_dim, n_heads * head_dim), n_groups)
        self.output = Grouped(lambda: nn.Linear(n_heads * head_dim, out_dim), n_groups)

    def forward(self, x: Tensor, graph: GraphBatch | Tensor | None = None) -> Tensor:
        """:param x: ``(batch, n_agents, in_dim)``; :param graph: groups only (neighbours are ignored).
        :return: ``(batch, n_agents, out_dim)``."""
        graph = graph if isinstance(graph, GraphBatch) else None
        return F.relu(self.output(F.relu(self.value(x, graph=graph)), graph=graph))


class HGRN(nn.Module):
    """Graph-recurrent network: encoder -> 2 communication hops -> skip concat -> GRUCell -> head.

    Agents of one group share parameters: with several groups (``group_n_actions``) every group has
    its own encoder, attention projections, GRU and head, and the outputs of the actions a group
    does not have are :data:`MASKED_OUTPUT` (so softmax, max and logsumexp over them ignore them).
    Observations of all groups arrive zero-padded to one width ``obs_dim``; the padding is always
    zero, so a group's encoder acts as one on its own observation width.

    :param obs_dim: observation features per agent (the widest group's).
    :param n_actions: outputs per agent (Q-values or logits; the largest group's action count).
    :param hidden_dim: hidden size ``H``.
    :param n_heads: attention heads.
    :param head_dim: features per head; None means ``hidden_dim // n_heads``.
    :param communication: ``"hgat"`` (graph attention, over every sender group), ``"gat"``
        (attention within the agent's own group only), ``"mean"`` (CommNet mean) or ``"none"``.
    :param recurrent: use a GRUCell on the ``3H`` skip concat; if False the head reads the concat
        directly and the recurrent state has width 0.
    :param group_n_actions: action count of every agent group (``None``: one group).
    :param mixed_precision: run the dense layers' matrix products in bfloat16 (``torch.autocast``);
        parameters, attention weights and the returned outputs and state stay float32. Faster at
        large sizes where the hardware has bfloat16 arithmetic (AVX512-BF16 or AMX, recent GPUs);
        ``benchmarks/throughput.py --sizes paper paper-bf16`` compares both.
    """

    def __init__(
        self,
        obs_dim: int,
        n_actions: int,
        hidden_dim: int = 64,
        n_heads: int = 4,
        head_dim: int | None = None,
        communication: str = "hgat",
        recurrent: bool = True,
        group_n_actions: Sequence[int] | None = None,
        mixed_precision: bool = False,
    ) -> None:
        super().__init__()
        if communication not in COMMUNICATIONS:
            raise ValueError(f"communication must be one of {COMMUNICATIONS}, got {communication!r}")
        _check_positive(obs_dim=obs_dim, n_actions=n_actions, hidden_dim=hidden_dim, n_heads=n_heads)
        head_dim = hidden_dim // n_heads if head_dim is None else head_dim
        _check_positive(head_dim=head_dim)
        group_n_actions = [n_actions] if group_n_actions is None else [int(n) for n in group_n_actions]
        if not group_n_actions or min(group_n_actions) < 1 or max(group_n_actions) != n_actions:
            raise ValueError(
                f"group_n_actions must be positive with maximum n_actions={n_actions}, got {group_n_actions}"
            )
        self.obs_dim = obs_dim
        self.hidden_dim = hidden_dim
        self.recurrent = recurrent
        self.mixed_precision = mixed_precision
        self.n_groups = n_groups = len(group_n_actions)
        self.register_buffer(
            "valid_actions",
            torch.arange(n_actions) < torch.tensor(group_n_actions).unsqueeze(1),
            persistent=False,
        )
        self.encoder = Grouped(lambda: nn.Sequential(nn.Linear(obs_dim, hidden_dim), nn.ReLU()), n_groups)
        self.comm1 = _make_communication(communication, hidden_dim, n_heads, head_dim, n_groups)
        self.comm2 = _make_communication(communication, hidden_dim, n_heads, head_dim, n_groups)
        self.gru = Grouped(lambda: nn.GRUCell(3 * hidden_dim, hidden_dim), n_groups) if recurrent else None
        head_in = hidden_dim if recurrent else 3 * hidden_dim
        self.head = Grouped(lambda: nn.Linear(head_in, n_actions), n_groups)

    @property
    def state_dim(self) -> int:
        """Width of the recurrent state per agent: ``hidden_dim`` if recurrent, else 0."""
        return self.hidden_dim if self.recurrent else 0

    def forward(
        self, obs: Tensor, neighbors: Tensor, hidden: Tensor, groups: Tensor | None = None
    ) -> tuple[Tensor, Tensor]:
        """One step for all agents.

        :param obs: ``(batch, n_agents, obs_dim)`` float observations.
        :param neighbors: ``(batch, n_agents, max_neighbors)`` agent indices, ``-1`` = no entry;
            ``max_neighbors`` may be 0.
        :param hidden: ``(batch, n_agents, state_dim)`` recurrent state fed in.
        :param groups: ``(batch, n_agents)`` group ids (needed with several groups).
        :return: outputs ``(batch, n_agents, n_actions)`` and the new state
            ``(batch, n_agents, state_dim)``.
        """
        self._check_inputs(obs, neighbors, hidden)
        graph = GraphBatch(neighbors, groups, self.n_groups)
        precision = (
            torch.autocast(obs.device.type, dtype=torch.bfloat16)
            if self.mixed_precision
            else contextlib.nullcontext()
        )
        with precision:
            encoded = self.encoder(obs, graph=graph)
            hop1 = self.comm1(encoded, graph)
            hop2 = self.comm2(hop1, graph)
            features = torch.cat([encoded, hop1, hop2], dim=-1)
            if self.gru is not None:
                rows = obs.shape[0] * obs.shape[1]
                hidden = self.gru(features.reshape(rows, -1), hidden.reshape(rows, -1), graph=graph)
                features = hidden = hidden.reshape(*obs.shape[:2], -1)
            out = self.head(features, graph=graph)
        if self.mixed_precision:
            out, hidden = out.float(), hidden.float()
        if self.n_groups > 1:
            valid = self.valid_actions[graph.row_groups].reshape(out.shape)
            out = out.masked_fill(~valid, MASKED_OUTPUT)
        return out, hidden

    def _check_inputs(self, obs: Tensor, neighbors: Tensor, hidden: Tensor) -> None:
        if obs.dim() != 3 or obs.shape[-1] != self.obs_dim:
            raise ValueError(f"obs must have shape (batch, n_agents, {self.obs_dim}), got {tuple(obs.shape)}")
        if neighbors.dim() != 3 or neighbors.shape[:2] != obs.shape[:2]:
            raise ValueError(
                f"neighbors must have shape (batch, n_agents, max_neighbors) = {tuple(obs.shape[:2])} + "
                f"(K,), got {tuple(neighbors.shape)}"
            )
        expected = (*obs.shape[:2], self.state_dim)
        if tuple(hidden.shape) != expected:
            raise ValueError(f"hidden must have shape {expected}, got {tuple(hidden.shape)}")


def _make_communication(
    communication: str, hidden_dim: int, n_heads: int, head_dim: int, n_groups: int
) -> nn.Module:
    if communication in ("hgat", "gat"):
        return GraphAttention(
            hidden_dim, hidden_dim, n_heads, head_dim, n_groups, across_groups=communication == "hgat"
        )
    if communication == "mean":
        return MeanCommunication(hidden_dim, hidden_dim, n_groups)
    return SelfOnly(hidden_dim, hidden_dim, n_heads, head_dim, n_groups)
