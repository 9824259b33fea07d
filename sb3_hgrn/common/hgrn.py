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

import math
import warnings
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn

PAPER_SIZE: dict = {"hidden_dim": 256, "n_heads": 4, "head_dim": 256}
"""Network size of the original HGRN (4 heads of width 256 on a hidden size of 256)."""

COMMUNICATIONS = ("hgat", "mean", "none")


def neighbor_columns(neighbors: Tensor, n_agents: int) -> tuple[Tensor, Tensor]:
    """Turn neighbour lists into flat gather indices with the self-loop in column 0.

    :param neighbors: ``(batch, n_agents, max_neighbors)`` integer agent indices, ``-1`` = no entry.
    :param n_agents: number of agents per graph.
    :return: ``columns`` of shape ``(max_neighbors + 1, batch * n_agents)`` with flat row indices
        ``b * n_agents + j`` into a ``(batch * n_agents, ...)`` tensor (entries that are empty or
        equal to the agent itself point at the agent and are masked), and ``mask`` of shape
        ``(batch * n_agents, max_neighbors + 1)``, True for the entries that take part (column 0,
        the agent itself, is always True).
    """
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

    Logits are sampled dot products at the listed entries only and the weighted sum of values is a
    sparse-dense product, so nothing of size ``(rows, K + 1, heads, head_dim)`` is formed; the
    backward pass uses the transposed pattern for the gradients of keys and values.
    """

    @staticmethod
    def forward(
        ctx, query: Tensor, key: Tensor, value: Tensor, pattern: _Pattern, mask: Tensor
    ) -> tuple[Tensor, Tensor]:
        """``query``/``key``/``value`` ``(rows, heads, head_dim)``, ``mask`` ``(rows, K + 1)``.
        Returns output ``(rows, heads, head_dim)`` and attention weights ``(rows, heads, K + 1)``."""
        rows, heads, head_dim = query.shape
        scaled_query = (query * head_dim**-0.5).reshape(-1, head_dim)
        key, value = key.reshape(-1, head_dim), value.reshape(-1, head_dim)
        logits = _sampled_dot(pattern, scaled_query, key).view(rows, heads, -1)
        weights = logits.masked_fill_(~mask.unsqueeze(1), -math.inf).softmax(dim=-1)
        out = _matmul(pattern, weights, value).view(rows, heads, head_dim)
        ctx.save_for_backward(scaled_query, key, value, weights)
        ctx.pattern = pattern
        ctx.mark_non_differentiable(weights)
        return out, weights

    @staticmethod
    def backward(ctx, grad_out: Tensor, _grad_weights: Tensor | None) -> tuple[Tensor | None, ...]:
        scaled_query, key, value, weights = ctx.saved_tensors
        pattern = ctx.pattern
        rows, heads, head_dim = grad_out.shape
        grad_out = grad_out.reshape(-1, head_dim)
        grad_weights = _sampled_dot(pattern, grad_out, value).view(weights.shape)
        grad_logits = weights * (grad_weights - (weights * grad_weights).sum(dim=-1, keepdim=True))
        grad_value = _matmul(pattern, weights, grad_out, transposed=True)
        grad_query = _matmul(pattern, grad_logits, key).mul_(head_dim**-0.5)
        grad_key = _matmul(pattern, grad_logits, scaled_query, transposed=True)
        shape = (rows, heads, head_dim)
        return grad_query.view(shape), grad_key.view(shape), grad_value.view(shape), None, None


def _check_positive(**sizes: int) -> None:
    for name, size in sizes.items():
        if size <= 0:
            raise ValueError(f"{name} must be positive, got {size}")


class GraphAttention(nn.Module):
    """Multi-head graph attention over neighbour lists, self-loop always included.

    ``q, k, v = ReLU(Linear(x))`` with ``n_heads * head_dim`` features each; agent ``i`` attends over
    itself and its valid listed neighbours with logits ``q_i . k_j / sqrt(head_dim)``; heads are
    concatenated and mapped by ``ReLU(Linear(n_heads * head_dim -> out_dim))``.

    :param in_dim: input features per agent.
    :param out_dim: output features per agent.
    :param n_heads: number of attention heads.
    :param head_dim: features per head.
    """

    def __init__(self, in_dim: int, out_dim: int, n_heads: int, head_dim: int) -> None:
        super().__init__()
        _check_positive(in_dim=in_dim, out_dim=out_dim, n_heads=n_heads, head_dim=head_dim)
        self.n_heads = n_heads
        self.head_dim = head_dim
        width = n_heads * head_dim
        self.query = nn.Linear(in_dim, width)
        self.key = nn.Linear(in_dim, width)
        self.value = nn.Linear(in_dim, width)
        self.output = nn.Linear(width, out_dim)

    def project(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Queries, keys and values ``(batch * n_agents, n_heads, head_dim)`` of ``x``
        ``(batch, n_agents, in_dim)``."""
        shape = (-1, self.n_heads, self.head_dim)
        return tuple(F.relu(layer(x)).reshape(shape) for layer in (self.query, self.key, self.value))

    def forward(
        self, x: Tensor, neighbors: Tensor, return_attention: bool = False
    ) -> Tensor | tuple[Tensor, Tensor]:
        """Attend over neighbours.

        :param x: ``(batch, n_agents, in_dim)`` agent features.
        :param neighbors: ``(batch, n_agents, max_neighbors)`` agent indices within the same graph,
            ``-1`` = no entry.
        :param return_attention: also return the attention weights.
        :return: ``(batch, n_agents, out_dim)``; with ``return_attention`` also the weights
            ``(batch, n_agents, n_heads, max_neighbors + 1)``, column 0 being the agent itself and
            column ``1 + m`` the list entry ``m`` (zero where the entry is empty or the agent itself).
        """
        batch, n_agents, _ = x.shape
        columns, mask = neighbor_columns(neighbors, n_agents)
        pattern = _attention_pattern(columns, self.n_heads)
        query, key, value = self.project(x)
        mixed, weights = _NeighborAttention.apply(query, key, value, pattern, mask)
        out = F.relu(self.output(mixed.reshape(batch, n_agents, -1)))
        if return_attention:
            return out, weights.reshape(batch, n_agents, self.n_heads, -1)
        return out


class MeanCommunication(nn.Module):
    """CommNet-style communication: ``ReLU(Linear([x_i, mean_j x_j]))`` over valid neighbours ``j != i``.

    The mean is zero for an agent without neighbours.

    :param in_dim: input features per agent.
    :param out_dim: output features per agent.
    """

    def __init__(self, in_dim: int, out_dim: int) -> None:
        super().__init__()
        _check_positive(in_dim=in_dim, out_dim=out_dim)
        self.output = nn.Linear(2 * in_dim, out_dim)

    def forward(self, x: Tensor, neighbors: Tensor) -> Tensor:
        """:param x: ``(batch, n_agents, in_dim)``; :param neighbors: ``(batch, n_agents, max_neighbors)``.
        :return: ``(batch, n_agents, out_dim)``."""
        batch, n_agents, in_dim = x.shape
        columns, mask = neighbor_columns(neighbors, n_agents)
        others = mask[:, 1:].t().unsqueeze(-1).to(x.dtype)  # (K, rows, 1)
        gathered = x.reshape(-1, in_dim).index_select(0, columns[1:].reshape(-1))
        total = (gathered.reshape(*others.shape[:2], in_dim) * others).sum(0)
        mean = total / others.sum(0).clamp(min=1.0)
        return F.relu(self.output(torch.cat([x, mean.reshape(batch, n_agents, in_dim)], dim=-1)))


class SelfOnly(nn.Module):
    """No communication (the "-G" ablation): attention over the agent alone.

    Equals :class:`GraphAttention` with an empty graph: ``ReLU(Linear(ReLU(Linear(x))))`` through
    ``n_heads * head_dim`` value features.

    :param in_dim: input features per agent.
    :param out_dim: output features per agent.
    :param n_heads: number of (value) heads.
    :param head_dim: features per head.
    """

    def __init__(self, in_dim: int, out_dim: int, n_heads: int, head_dim: int) -> None:
        super().__init__()
        _check_positive(in_dim=in_dim, out_dim=out_dim, n_heads=n_heads, head_dim=head_dim)
        self.value = nn.Linear(in_dim, n_heads * head_dim)
        self.output = nn.Linear(n_heads * head_dim, out_dim)

    def forward(self, x: Tensor, neighbors: Tensor) -> Tensor:
        """:param x: ``(batch, n_agents, in_dim)``; :param neighbors: ignored.
        :return: ``(batch, n_agents, out_dim)``."""
        return F.relu(self.output(F.relu(self.value(x))))


class HGRN(nn.Module):
    """Graph-recurrent network: encoder -> 2 communication hops -> skip concat -> GRUCell -> head.

    :param obs_dim: observation features per agent.
    :param n_actions: outputs per agent (Q-values or logits).
    :param hidden_dim: hidden size ``H``.
    :param n_heads: attention heads.
    :param head_dim: features per head; None means ``hidden_dim // n_heads``.
    :param communication: ``"hgat"`` (graph attention), ``"mean"`` (CommNet mean) or ``"none"``
        (no communication).
    :param recurrent: use a GRUCell on the ``3H`` skip concat; if False the head reads the concat
        directly and the recurrent state has width 0.
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
    ) -> None:
        super().__init__()
        if communication not in COMMUNICATIONS:
            raise ValueError(f"communication must be one of {COMMUNICATIONS}, got {communication!r}")
        _check_positive(obs_dim=obs_dim, n_actions=n_actions, hidden_dim=hidden_dim, n_heads=n_heads)
        head_dim = hidden_dim // n_heads if head_dim is None else head_dim
        _check_positive(head_dim=head_dim)
        self.obs_dim = obs_dim
        self.hidden_dim = hidden_dim
        self.recurrent = recurrent
        self.encoder = nn.Sequential(nn.Linear(obs_dim, hidden_dim), nn.ReLU())
        self.comm1 = _make_communication(communication, hidden_dim, n_heads, head_dim)
        self.comm2 = _make_communication(communication, hidden_dim, n_heads, head_dim)
        self.gru = nn.GRUCell(3 * hidden_dim, hidden_dim) if recurrent else None
        self.head = nn.Linear(hidden_dim if recurrent else 3 * hidden_dim, n_actions)

    @property
    def state_dim(self) -> int:
        """Width of the recurrent state per agent: ``hidden_dim`` if recurrent, else 0."""
        return self.hidden_dim if self.recurrent else 0

    def forward(self, obs: Tensor, neighbors: Tensor, hidden: Tensor) -> tuple[Tensor, Tensor]:
        """One step for all agents.

        :param obs: ``(batch, n_agents, obs_dim)`` float observations.
        :param neighbors: ``(batch, n_agents, max_neighbors)`` agent indices, ``-1`` = no entry;
            ``max_neighbors`` may be 0.
        :param hidden: ``(batch, n_agents, state_dim)`` recurrent state fed in.
        :return: outputs ``(batch, n_agents, n_actions)`` and the new state
            ``(batch, n_agents, state_dim)``.
        """
        self._check_inputs(obs, neighbors, hidden)
        batch, n_agents, _ = obs.shape
        encoded = self.encoder(obs)
        hop1 = self.comm1(encoded, neighbors)
        hop2 = self.comm2(hop1, neighbors)
        features = torch.cat([encoded, hop1, hop2], dim=-1)
        if self.gru is None:
            return self.head(features), hidden
        new_hidden = self.gru(
            features.reshape(batch * n_agents, -1), hidden.reshape(batch * n_agents, -1)
        ).reshape(batch, n_agents, -1)
        return self.head(new_hidden), new_hidden

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


def _make_communication(communication: str, hidden_dim: int, n_heads: int, head_dim: int) -> nn.Module:
    if communication == "hgat":
        return GraphAttention(hidden_dim, hidden_dim, n_heads, head_dim)
    if communication == "mean":
        return MeanCommunication(hidden_dim, hidden_dim)
    return SelfOnly(hidden_dim, hidden_dim, n_heads, head_dim)
