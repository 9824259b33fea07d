"""HGRN: graph-recurrent network over neighbour lists (pure torch).

Agents of ``batch`` independent graphs are processed together, each graph given as neighbour lists
``(batch, n_agents, max_neighbors)`` (agent indices within the same graph, ``-1`` = no entry). Every
communication layer always adds the agent itself (the self-loop). The attention layers run on the
sparse kernel of :mod:`sb3_hgrn.common.attention`, which never forms an ``n_agents x n_agents``
matrix.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable, Sequence
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from sb3_hgrn.common.attention import GraphBatch, RowGroups, as_graph_batch, neighbor_attention
from sb3_hgrn.validation import is_integer

PAPER_SIZE: dict = {"hidden_dim": 256, "n_heads": 4, "head_dim": 256}
"""Network size of the original HGRN (4 heads of width 256 on a hidden size of 256)."""

COMMUNICATIONS = ("hgat", "gat", "mean", "none")

MASKED_OUTPUT = -1e9
"""Output of the actions an agent's group does not have: softmax gives them probability 0."""


def _check_positive(**sizes: int) -> None:
    for name, size in sizes.items():
        if size <= 0:
            raise ValueError(f"{name} must be positive, got {size}")


class Grouped(nn.Module):
    """One copy of a module per agent group: every row goes through its agent's group's copy.

    :param make: builds one copy.
    :param n_groups: number of groups.
    :param item_dims: ``None`` for copies that take any leading dimensions (as ``nn.Linear``; rows
        are then feature vectors), or the number of trailing dimensions of one row (a whole
        observation): the copies then always see the rows flattened to ``(rows, *item_shape)``.
    """

    def __init__(
        self, make: Callable[[], nn.Module], n_groups: int = 1, item_dims: int | None = None
    ) -> None:
        super().__init__()
        _check_positive(n_groups=n_groups, item_dims=1 if item_dims is None else item_dims)
        self.members = nn.ModuleList(make() for _ in range(n_groups))
        self.item_dims = item_dims

    def __getitem__(self, group: int) -> nn.Module:
        return self.members[group]

    def forward(self, *inputs: Tensor, graph: GraphBatch | RowGroups | None = None) -> Tensor:
        """Apply the copies to ``inputs`` whose leading dimensions are the agents of ``graph``
        (``(batch, n_agents, *item_shape)`` or flattened ``(batch * n_agents, *item_shape)``); one
        group needs no graph. :return: ``(*leading, out_features)``."""
        if len(self.members) == 1 and self.item_dims is None:
            return self.members[0](*inputs)
        split = inputs[0].dim() - (self.item_dims or 1)
        leading = inputs[0].shape[:split]
        flat = [x.reshape(-1, *x.shape[split:]) for x in inputs]
        if len(self.members) == 1:
            out = self.members[0](*flat)
        else:
            outputs = [
                member(*(x.index_select(0, rows) for x in flat))
                for member, rows in zip(self.members, graph.group_rows, strict=True)
            ]
            out = torch.cat(outputs).index_select(0, graph.group_inverse)
        return out.reshape(*leading, out.shape[-1])


class GraphAttention(nn.Module):
    """Multi-head (heterogeneous) graph attention over neighbour lists, self-loop always included.

    ``q, k, v = ReLU(Linear(x))`` with ``n_heads * head_dim`` features each; agent ``i`` attends over
    itself and the distinct agents of its list (each once, however often listed) with logits
    ``q_i . k_j / sqrt(head_dim)``; heads are concatenated and mapped by
    ``ReLU(Linear(n_heads * head_dim -> out_dim))``.

    With several agent groups (HGAT) the receiver's group owns the query and the output map, the
    sender's group owns the key and value; ``across_groups=True`` attends over the neighbours of each
    sender group separately, giving one message per group (zero if the agent has no neighbour of that
    group), and maps the messages to ``out_dim`` with the receiver group's :class:`GroupMessageMap`;
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
        self.n_messages = n_groups if across_groups else 1
        self.query = Grouped(lambda: nn.Linear(in_dim, width), n_groups)
        self.key = Grouped(lambda: nn.Linear(in_dim, width), n_groups)
        self.value = Grouped(lambda: nn.Linear(in_dim, width), n_groups)
        if self.n_messages == 1:
            self.output = Grouped(lambda: nn.Linear(width, out_dim), n_groups)
        else:
            self.output = Grouped(lambda: GroupMessageMap(self.n_messages, width, out_dim), n_groups)

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
            column ``1 + m`` the list entry ``m`` (zero where the entry is empty, the agent itself, an
            agent listed before, or not attended); with several sender groups the weights of each
            group sum to one.
        """
        graph = as_graph_batch(graph)
        batch, n_agents, _ = x.shape
        query, key, value = self.project(x, graph)
        segments = graph.segments(self.across_groups)
        dtype = torch.promote_types(query.dtype, torch.float32)  # bfloat16 under autocast -> float32
        with torch.autocast(x.device.type, enabled=False):  # the sparse kernels run in full precision
            mixed, weights = neighbor_attention(
                query.to(dtype), key.to(dtype), value.to(dtype), graph.pattern(self.n_heads), segments
            )
        out = self._mapped(mixed, x, graph)
        if return_attention:
            return out, graph.list_weights(weights).reshape(batch, n_agents, self.n_heads, -1)
        return out

    def gathered(
        self, x: Tensor, graph: GraphBatch, columns: Tensor, mask: Tensor, segments: Sequence[Tensor]
    ) -> Tensor:
        """:meth:`forward` with every entry's keys and values gathered (``(rows, E, n_heads,
        head_dim)``) instead of the sparse kernel: no sparse tensor, so ``torch.compile`` can take the
        whole network as one graph (see :class:`HGRN`'s ``compile_network``).

        :param columns: ``(rows, E)`` the graph's :attr:`GraphBatch.columns`.
        :param mask: ``(rows, E)`` its :attr:`GraphBatch.mask` (unused: the segments hold it).
        :param segments: its :meth:`GraphBatch.segments` for this layer.
        :return: ``(batch, n_agents, out_dim)``.
        """
        query, key, value = self.project(x, graph)
        dtype = torch.promote_types(query.dtype, torch.float32)
        with torch.autocast(x.device.type, enabled=False):  # in full precision, as the sparse kernel
            query, key, value = query.to(dtype), key.to(dtype), value.to(dtype)
            keys, values = key[columns], value[columns]  # (rows, E, n_heads, head_dim)
            logits = (query.unsqueeze(1) * keys).sum(-1) * self.head_dim**-0.5  # (rows, E, n_heads)
            messages = []
            for segment in segments:
                weights = logits.masked_fill(~segment.unsqueeze(-1), -math.inf).softmax(dim=1)
                if len(segments) > 1:  # a row without entries in a segment: its message is zero
                    weights = weights.nan_to_num(0.0)
                messages.append((weights.unsqueeze(-1) * values).sum(1))  # (rows, n_heads, head_dim)
            mixed = torch.stack(messages, dim=1)
        return self._mapped(mixed, x, graph)

    def _mapped(self, mixed: Tensor, x: Tensor, graph: GraphBatch) -> Tensor:
        """The output map of the messages ``(rows, n_messages, n_heads, head_dim)``:
        ``(batch, n_agents, out_dim)``."""
        out = self.output(mixed.reshape(*x.shape[:2], -1), graph=graph)
        return F.relu(out) if self.n_messages == 1 else out


class GroupMessageMap(nn.Module):
    """The HGAT output map of one receiver group: the message of each sender group goes through its
    own ``ReLU(Linear(width -> out_dim))``, and their concatenation in group order through
    ``Linear(n_senders * out_dim -> out_dim)`` without activation (the paper's
    ``g_i = W (g_i^1 | ... | g_i^K)`` after a map per receiver-sender pair, as in the original code).

    :param n_senders: number of sender groups.
    :param width: features of one message.
    :param out_dim: output features.
    """

    def __init__(self, n_senders: int, width: int, out_dim: int) -> None:
        super().__init__()
        self.per_sender = nn.ModuleList(nn.Linear(width, out_dim) for _ in range(n_senders))
        self.combine = nn.Linear(n_senders * out_dim, out_dim)

    def forward(self, messages: Tensor) -> Tensor:
        """:param messages: ``(..., n_senders * width)``, sender groups in order.
        :return: ``(..., out_dim)``."""
        parts = messages.chunk(len(self.per_sender), dim=-1)
        mapped = [F.relu(layer(part)) for layer, part in zip(self.per_sender, parts, strict=True)]
        return self.combine(torch.cat(mapped, dim=-1))


class MeanCommunication(nn.Module):
    """CommNet-style communication: ``ReLU(Linear([x_i, mean_j x_j]))`` over the distinct listed
    neighbours ``j != i``.

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
        graph = as_graph_batch(graph)
        return self.gathered(x, graph, graph.columns, graph.mask, ())

    def gathered(
        self, x: Tensor, graph: GraphBatch, columns: Tensor, mask: Tensor, segments: Sequence[Tensor]
    ) -> Tensor:
        """:meth:`forward` with the graph's ``columns`` and ``mask`` ``(rows, E)`` given (the
        ``segments`` are unused), as :meth:`GraphAttention.gathered`."""
        batch, n_agents, in_dim = x.shape
        own = torch.arange(batch * n_agents, device=x.device).unsqueeze(1)
        others = (mask & (columns != own)).unsqueeze(-1).to(x.dtype)  # (rows, E, 1)
        gathered = x.reshape(-1, in_dim).index_select(0, columns.reshape(-1))
        total = (gathered.reshape(*others.shape[:2], in_dim) * others).sum(1)
        mean = total / others.sum(1).clamp(min=1.0)
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

    def gathered(
        self, x: Tensor, graph: GraphBatch, columns: None, mask: None, segments: Sequence[Tensor]
    ) -> Tensor:
        """:meth:`forward` (no entries are read), as :meth:`GraphAttention.gathered`."""
        return self.forward(x, graph)


class HGRN(nn.Module):
    """Graph-recurrent network: encoder -> 2 communication hops -> skip concat -> GRUCell -> head.

    Agents of one group share parameters: with several groups (``group_n_actions``) every group has
    its own encoder, attention projections, GRU and head, and the outputs of the actions a group
    does not have are :data:`MASKED_OUTPUT` (so softmax, max and logsumexp over them ignore them).
    Observations of all groups arrive zero-padded to one width ``obs_dim``; the padding is always
    zero, so a group's encoder acts as one on its own observation width.

    Observations of any shape are flattened before the encoder, or mapped by a features extractor
    (one per group) whose features then take the observation's place.

    :param obs_dim: observation features per agent (the widest group's), or the shape of one
        agent's observation.
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
    :param features_extractor: builds one features extractor (called once per group): a module
        mapping observations ``(rows, *obs_shape)`` float32 to ``(rows, features_dim)``, with an
        integer attribute ``features_dim`` (SB3's ``BaseFeaturesExtractor``). ``None``: the
        flattened observation is the encoder's input.
    :param compile_network: run :meth:`features` (the encoder and both communication hops, the bulk
        of the network's work) under ``torch.compile``: ``True`` with its defaults, or a dict of its
        keyword arguments (``{"mode": "max-autotune"}``, ``{"backend": "aot_eager"}``). The
        attention then gathers every entry's keys and values (:meth:`GraphAttention.gathered`)
        instead of the sparse kernel, which the compiler cannot take. The first call of every new
        input shape compiles (about 20 s on a laptop CPU with the default backend, which needs a C++
        compiler), later calls run the compiled code: ``predict`` is faster, a whole training run
        was not (``benchmarks/compiled_network.py``, ``docs/results_speed.md``). ``False``: eager.
    """

    def __init__(
        self,
        obs_dim: int | Sequence[int],
        n_actions: int,
        hidden_dim: int = 64,
        n_heads: int = 4,
        head_dim: int | None = None,
        communication: str = "hgat",
        recurrent: bool = True,
        group_n_actions: Sequence[int] | None = None,
        mixed_precision: bool = False,
        features_extractor: Callable[[], nn.Module] | None = None,
        compile_network: bool | dict = False,
    ) -> None:
        super().__init__()
        self.compile_options = compile_options(compile_network)
        if communication not in COMMUNICATIONS:
            raise ValueError(f"communication must be one of {COMMUNICATIONS}, got {communication!r}")
        self.obs_shape = (int(obs_dim),) if isinstance(obs_dim, int) else tuple(int(n) for n in obs_dim)
        if not self.obs_shape or min(self.obs_shape) < 1:
            raise ValueError(f"obs_dim must be a positive size or shape, got {obs_dim}")
        obs_dim = math.prod(self.obs_shape)
        _check_positive(n_actions=n_actions, hidden_dim=hidden_dim, n_heads=n_heads)
        head_dim = hidden_dim // n_heads if head_dim is None else head_dim
        _check_positive(head_dim=head_dim)
        group_n_actions = [n_actions] if group_n_actions is None else [int(n) for n in group_n_actions]
        if not group_n_actions or min(group_n_actions) < 1 or max(group_n_actions) != n_actions:
            raise ValueError(
                f"group_n_actions must be positive with maximum n_actions={n_actions}, got {group_n_actions}"
            )
        self.obs_dim = obs_dim  # flattened width
        self.hidden_dim = hidden_dim
        self.recurrent = recurrent
        self.mixed_precision = mixed_precision
        self.n_groups = n_groups = len(group_n_actions)
        self.register_buffer(
            "valid_actions",
            torch.arange(n_actions) < torch.tensor(group_n_actions).unsqueeze(1),
            persistent=False,
        )
        self.features_extractor = None
        encoder_in = obs_dim
        if features_extractor is not None:
            self.features_extractor = Grouped(features_extractor, n_groups, item_dims=len(self.obs_shape))
            encoder_in = checked_features_dim(self.features_extractor[0], self.obs_shape)
        self.encoder = Grouped(lambda: nn.Sequential(nn.Linear(encoder_in, hidden_dim), nn.ReLU()), n_groups)
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
        self, obs: Tensor, neighbors: Tensor | GraphBatch, hidden: Tensor, groups: Tensor | None = None
    ) -> tuple[Tensor, Tensor]:
        """One step for all agents.

        :param obs: ``(batch, n_agents, *obs_shape)`` float observations.
        :param neighbors: ``(batch, n_agents, max_neighbors)`` agent indices, ``-1`` = no entry
            (``max_neighbors`` may be 0), or the :class:`GraphBatch` of these graphs built with this
            network's ``n_groups`` (and the groups), which several networks can share.
        :param hidden: ``(batch, n_agents, state_dim)`` recurrent state fed in.
        :param groups: ``(batch, n_agents)`` group ids (needed with several groups and neighbour
            lists; a :class:`GraphBatch` carries them already).
        :return: outputs ``(batch, n_agents, n_actions)`` and the new state
            ``(batch, n_agents, state_dim)``.
        """
        self._check_inputs(obs, neighbors, hidden, groups)
        graph = (
            neighbors if isinstance(neighbors, GraphBatch) else GraphBatch(neighbors, groups, self.n_groups)
        )
        memory = self.remember(self.features(obs, graph), hidden, graph)
        return self.outputs(memory, graph), memory if self.gru is not None else hidden

    def _precision(self, device: torch.device) -> contextlib.AbstractContextManager:
        """bfloat16 autocast for the dense layers with ``mixed_precision``, else nothing."""
        if self.mixed_precision:
            return torch.autocast(device.type, dtype=torch.bfloat16)
        return contextlib.nullcontext()

    def features(self, obs: Tensor, graph: GraphBatch) -> Tensor:
        """The skip concat ``[encoded, hop 1, hop 2]`` ``(batch, n_agents, 3 * hidden_dim)`` of
        observations ``(batch, n_agents, *obs_shape)``: everything before the memory, so it can be
        computed for many steps of a sequence at once."""
        if self.compile_options is not None:
            return self._compiled_features(obs, graph)
        with self._precision(obs.device):
            encoded = self.encode(obs, graph)
            hop1 = self.comm1(encoded, graph)
            hop2 = self.comm2(hop1, graph)
            return torch.cat([encoded, hop1, hop2], dim=-1)

    def _compiled_features(self, obs: Tensor, graph: GraphBatch) -> Tensor:
        """:meth:`features` through the compiled gather form; the graph's entries are computed first,
        outside the compiled code."""
        columns = mask = None
        segments: tuple[Tensor, ...] = ()
        if isinstance(self.comm1, (GraphAttention, MeanCommunication)):
            columns, mask = graph.columns, graph.mask
        if isinstance(self.comm1, GraphAttention):
            segments = tuple(graph.segments(self.comm1.across_groups))
        compiled = _compiled_gathered_features(self.compile_options)
        try:
            with torch._dynamo.config.patch(recompile_limit=RECOMPILE_LIMIT):
                return compiled(self, obs, graph, columns, mask, segments)
        except torch._dynamo.exc.BackendCompilerFailed as error:
            raise RuntimeError(
                f"compile_network={self.compile_options or True} could not compile the network: "
                f"{error.inner_exception!r}. torch.compile's default backend needs a working C++ "
                "compiler; compile_network=False runs the network eagerly."
            ) from error

    def remember(self, features: Tensor, hidden: Tensor, graph: GraphBatch | RowGroups) -> Tensor:
        """The GRU step: the new state ``(batch, n_agents, hidden_dim)`` from :meth:`features` and the
        state ``hidden``; without recurrence the features themselves (the head reads them)."""
        if self.gru is None:
            return features
        rows = features.shape[0] * features.shape[1]
        with self._precision(features.device):
            new = self.gru(features.reshape(rows, -1), hidden.reshape(rows, -1), graph=graph)
        return new.float().reshape(*features.shape[:2], -1)

    def outputs(self, memory: Tensor, graph: GraphBatch | RowGroups) -> Tensor:
        """The head's outputs ``(batch, n_agents, n_actions)`` of :meth:`remember`'s result (float32;
        a group's missing actions at :data:`MASKED_OUTPUT`)."""
        with self._precision(memory.device):
            out = self.head(memory, graph=graph)
        out = out.float()
        if self.n_groups > 1:
            valid = self.valid_actions[graph.row_groups].reshape(out.shape)
            out = out.masked_fill(~valid, MASKED_OUTPUT)
        return out

    def encode(self, obs: Tensor, graph: GraphBatch) -> Tensor:
        """The encoder's output ``(batch, n_agents, hidden_dim)`` for observations ``(batch, n_agents,
        *obs_shape)``: of the features extractor's features, or of the flattened observations."""
        if self.features_extractor is None:
            features = obs.reshape(*obs.shape[:2], self.obs_dim)
        else:
            features = self.features_extractor(obs, graph=graph)
        return self.encoder(features, graph=graph)

    def _check_inputs(
        self, obs: Tensor, neighbors: Tensor | GraphBatch, hidden: Tensor, groups: Tensor | None
    ) -> None:
        if obs.dim() != 2 + len(self.obs_shape) or tuple(obs.shape[2:]) != self.obs_shape:
            raise ValueError(
                f"obs must have shape (batch, n_agents, {', '.join(map(str, self.obs_shape))}), "
                f"got {tuple(obs.shape)}"
            )
        if isinstance(neighbors, GraphBatch):
            if (neighbors.batch, neighbors.n_agents) != tuple(obs.shape[:2]):
                raise ValueError(
                    f"The GraphBatch holds {neighbors.batch} graphs of {neighbors.n_agents} agents, the "
                    f"observations {tuple(obs.shape[:2])}."
                )
            if neighbors.n_groups != self.n_groups or groups is not None:
                raise ValueError(
                    f"A GraphBatch for this network must be built with n_groups={self.n_groups} and "
                    "the groups, which are then not passed again."
                )
        elif neighbors.dim() != 3 or neighbors.shape[:2] != obs.shape[:2]:
            raise ValueError(
                f"neighbors must have shape (batch, n_agents, max_neighbors) = {tuple(obs.shape[:2])} + "
                f"(K,), got {tuple(neighbors.shape)}"
            )
        expected = (*obs.shape[:2], self.state_dim)
        if tuple(hidden.shape) != expected:
            raise ValueError(f"hidden must have shape {expected}, got {tuple(hidden.shape)}")


def checked_features_dim(extractor: nn.Module, obs_shape: tuple[int, ...]) -> int:
    """The ``features_dim`` of a features extractor, after checking that it maps a batch of zero
    observations ``(2, *obs_shape)`` to ``(2, features_dim)``; a ``ValueError`` (``TypeError`` for a
    missing ``features_dim``) names the extractor and what it got wrong."""
    name = type(extractor).__name__
    features_dim = getattr(extractor, "features_dim", None)
    if not is_integer(features_dim) or features_dim < 1:
        raise TypeError(
            f"The features extractor {name} needs a positive integer features_dim attribute (the width of "
            f"its output, as SB3's BaseFeaturesExtractor has), got {features_dim!r}."
        )
    probe = torch.zeros(2, *obs_shape)
    was_training = extractor.training
    extractor.train(False)
    try:
        with torch.no_grad():
            out = extractor(probe)
    except Exception as error:
        raise ValueError(
            f"The features extractor {name} fails on observations of shape {tuple(probe.shape)} "
            f"(batch, *obs_shape): {error}"
        ) from error
    finally:
        extractor.train(was_training)
    if not isinstance(out, Tensor) or tuple(out.shape) != (2, features_dim):
        got = tuple(out.shape) if isinstance(out, Tensor) else type(out).__name__
        raise ValueError(
            f"The features extractor {name} maps observations of shape {tuple(probe.shape)} (batch, "
            f"*obs_shape) to {got}; it must return (batch, features_dim) = (2, {features_dim})."
        )
    return features_dim


def compile_options(compile_network: bool | dict) -> dict | None:
    """The ``torch.compile`` keyword arguments of HGRN's ``compile_network`` (``None``: eager)."""
    if compile_network is False:
        return None
    if compile_network is True:
        return {}
    if isinstance(compile_network, dict) and all(isinstance(key, str) for key in compile_network):
        return dict(compile_network)
    raise ValueError(
        f"compile_network must be True, False or a dict of torch.compile's keyword arguments, got "
        f"{compile_network!r}."
    )


def _gathered_features(
    network: HGRN,
    obs: Tensor,
    graph: GraphBatch,
    columns: Tensor | None,
    mask: Tensor | None,
    segments: tuple[Tensor, ...],
) -> Tensor:
    """:meth:`HGRN.features` of ``network`` with the communication layers' ``gathered`` forms."""
    with network._precision(obs.device):
        encoded = network.encode(obs, graph)
        hop1 = network.comm1.gathered(encoded, graph, columns, mask, segments)
        hop2 = network.comm2.gathered(hop1, graph, columns, mask, segments)
        return torch.cat([encoded, hop1, hop2], dim=-1)


_COMPILED_FEATURES: dict[str, Callable[..., Tensor]] = {}

RECOMPILE_LIMIT = 64
"""Compiled versions of :func:`_gathered_features` torch keeps per process (its default, 8, is
reached by a process that builds a few models: every network shape, input shape and gradient mode
is one); past it the gather form would run uncompiled, slower than the sparse kernel."""


def _compiled_gathered_features(options: dict[str, Any]) -> Callable[..., Tensor]:
    """One compiled :func:`_gathered_features` per set of ``torch.compile`` options, shared by every
    network (it takes the network as an argument, so each network runs with its own parameters)."""
    key = repr(sorted(options.items()))
    if key not in _COMPILED_FEATURES:
        _COMPILED_FEATURES[key] = torch.compile(_gathered_features, **options)
    return _COMPILED_FEATURES[key]


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
