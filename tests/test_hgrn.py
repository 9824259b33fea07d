"""Tests of the HGRN network and its communication layers against dense hand-written references."""

import math
import traceback

import pytest
import torch
import torch.nn.functional as F
from torch.utils._python_dispatch import TorchDispatchMode

from sb3_hgrn.common.attention import GraphBatch, NeighborAttention
from sb3_hgrn.common.hgrn import HGRN, MASKED_OUTPUT, PAPER_SIZE, GraphAttention, MeanCommunication, SelfOnly
from sb3_hgrn.common.off_policy import unroll

IN_DIM, OUT_DIM, HEADS, HEAD_DIM = 6, 7, 2, 3

# Two graphs of 5 agents, lists without self; agent 4 of graph 0 is isolated.
NEIGHBORS = torch.tensor(
    [
        [[1, 2, -1], [0, -1, -1], [3, 0, 1], [2, -1, -1], [-1, -1, -1]],
        [[4, -1, -1], [2, 3, 4], [-1, 1, -1], [0, 4, -1], [3, 2, 1]],
    ]
)
# The same graphs, with the agent itself inserted at different positions of its own list.
NEIGHBORS_WITH_SELF = torch.tensor(
    [
        [[0, 1, 2, -1], [0, 1, -1, -1], [3, 2, 0, 1], [2, 3, -1, -1], [-1, 4, -1, -1]],
        [[4, -1, -1, 0], [2, 3, 1, 4], [-1, 1, 2, -1], [0, 4, 3, -1], [4, 3, 2, 1]],
    ]
)


def dense_adjacency(neighbors: torch.Tensor) -> torch.Tensor:
    """``(batch, n, n)`` bool adjacency with self-loops, built entry by entry."""
    batch, n, _ = neighbors.shape
    adjacency = torch.eye(n, dtype=torch.bool).repeat(batch, 1, 1)
    for b in range(batch):
        for i in range(n):
            for j in neighbors[b, i].tolist():
                if j >= 0:
                    adjacency[b, i, j] = True
    return adjacency


def dense_attention(
    layer: GraphAttention, x: torch.Tensor, adjacency: torch.Tensor, groups: torch.Tensor | None = None
):
    """Reference output ``(batch, n, out)`` and weights ``(batch, n, heads, n)`` with a dense softmax
    over the masked ``n x n`` logits of every head. With ``groups`` ``(batch, n)`` every agent goes
    through its group's copies (receiver: query and output, sender: key and value) and the softmax
    runs per sender group (HGAT, messages concatenated in group order) or over the own group."""
    batch, n, _ = x.shape
    heads, dim = layer.n_heads, layer.head_dim
    groups = torch.zeros(batch, n, dtype=torch.long, device=x.device) if groups is None else groups

    def by_group(grouped, inputs):
        outputs = torch.stack([member(inputs) for member in grouped.members])  # (n_groups, batch, n, out)
        return outputs.gather(0, groups[None, ..., None].expand(1, batch, n, outputs.shape[-1]))[0]

    q, k, v = (
        F.relu(by_group(lin, x)).reshape(batch, n, heads, dim)
        for lin in (layer.query, layer.key, layer.value)
    )
    logits = torch.einsum("bihd,bjhd->bihj", q, k) / math.sqrt(dim)
    senders = groups.unsqueeze(1)  # (batch, 1, n): group of agent j
    if layer.across_groups:
        masks = [adjacency & (senders == group) for group in range(len(layer.query.members))]
    else:
        masks = [adjacency & (senders == groups.unsqueeze(2))]
    weights, messages = 0.0, []
    for mask in masks:
        mask = mask.unsqueeze(2)  # (batch, n, 1, n)
        segment = logits.masked_fill(~mask, -math.inf).where(mask.any(-1, keepdim=True), 0.0)
        segment = segment.softmax(dim=-1) * mask  # zero for a row without entries in the segment
        weights = weights + segment
        messages.append(torch.einsum("bihj,bjhd->bihd", segment, v).reshape(batch, n, heads * dim))
    out = by_group(layer.output, torch.cat(messages, dim=-1))
    return (F.relu(out) if layer.n_messages == 1 else out), weights


def dense_list_weights(weights: torch.Tensor, neighbors: torch.Tensor) -> torch.Tensor:
    """Dense weights ``(batch, n, heads, n)`` laid out over the lists ``(batch, n, heads, K + 1)``:
    column 0 the agent itself, ``1 + m`` entry ``m`` if it names another agent for the first time."""
    batch, n, width = neighbors.shape
    expected = torch.zeros(*weights.shape[:3], width + 1, dtype=weights.dtype, device=weights.device)
    for b in range(batch):
        for i in range(n):
            expected[b, i, :, 0] = weights[b, i, :, i]
            seen = {i}
            for m, j in enumerate(neighbors[b, i].tolist()):
                if j >= 0 and j not in seen:
                    expected[b, i, :, m + 1] = weights[b, i, :, j]
                    seen.add(j)
    return expected


def random_lists(batch: int, n_agents: int, width: int, seed: int) -> torch.Tensor:
    """Random lists ``(batch, n_agents, width)`` with empty entries, self entries and repeats; agent 0
    of graph 0 lists nobody, agent 1 only itself (repeatedly), agent 2 lists agent 3 twice first."""
    generator = torch.Generator().manual_seed(seed)
    neighbors = torch.randint(-1, n_agents, (batch, n_agents, width), generator=generator)
    neighbors[0, 0] = -1
    neighbors[0, 1] = 1
    neighbors[0, 2, :2] = 3
    return neighbors


DEVICES = [
    "cpu",
    pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")),
]


@pytest.fixture
def layer() -> GraphAttention:
    torch.manual_seed(0)
    return GraphAttention(IN_DIM, OUT_DIM, HEADS, HEAD_DIM).double()


@pytest.fixture
def x() -> torch.Tensor:
    torch.manual_seed(1)
    return torch.randn(2, 5, IN_DIM, dtype=torch.double)


@pytest.mark.parametrize("neighbors", [NEIGHBORS, NEIGHBORS_WITH_SELF])
def test_attention_matches_dense_reference(layer, x, neighbors):
    expected, _ = dense_attention(layer, x, dense_adjacency(NEIGHBORS))
    torch.testing.assert_close(layer(x, neighbors), expected)


@pytest.mark.parametrize("neighbors", [NEIGHBORS, NEIGHBORS_WITH_SELF])
def test_attention_gradcheck(layer, x, neighbors):
    x.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda inp: layer(inp, neighbors), (x,))


def test_attention_without_grad_matches_with_grad(layer, x):
    with torch.no_grad():
        out, weights = layer(x, NEIGHBORS, return_attention=True)
    expected, expected_weights = layer(x.requires_grad_(True), NEIGHBORS, return_attention=True)
    torch.testing.assert_close(out, expected.detach())
    torch.testing.assert_close(weights, expected_weights)


def test_attention_float32_paper_width_matches_dense_reference():
    torch.manual_seed(0)
    layer = GraphAttention(32, 32, 4, 256)
    x = torch.randn(3, 20, 32)
    neighbors = torch.stack([torch.randperm(20)[:6] for _ in range(60)]).reshape(3, 20, 6)
    neighbors[torch.rand(3, 20, 6) < 0.3] = -1  # lists without repeated entries, some empty slots
    expected, _ = dense_attention(layer.double(), x.double(), dense_adjacency(neighbors))
    torch.testing.assert_close(layer.float()(x, neighbors), expected.float(), rtol=1e-4, atol=1e-5)


def test_attention_gradients_match_dense_reference(layer, x):
    weight = torch.randn(2, 5, OUT_DIM, dtype=torch.double)
    params = [x.requires_grad_(True), *layer.parameters()]
    grads = torch.autograd.grad((layer(x, NEIGHBORS) * weight).sum(), params)
    expected, _ = dense_attention(layer, x, dense_adjacency(NEIGHBORS))
    expected_grads = torch.autograd.grad((expected * weight).sum(), params)
    for grad, expected_grad in zip(grads, expected_grads, strict=True):
        torch.testing.assert_close(grad, expected_grad)


def test_attention_weights(layer, x):
    _, dense_weights = dense_attention(layer, x, dense_adjacency(NEIGHBORS))
    _, weights = layer(x, NEIGHBORS, return_attention=True)
    assert weights.shape == (2, 5, HEADS, NEIGHBORS.shape[2] + 1)
    torch.testing.assert_close(weights.sum(-1), torch.ones(2, 5, HEADS, dtype=torch.double))
    for b in range(2):
        for i in range(5):
            torch.testing.assert_close(weights[b, i, :, 0], dense_weights[b, i, :, i])
            for m, j in enumerate(NEIGHBORS[b, i].tolist()):
                expected = dense_weights[b, i, :, j] if j >= 0 else torch.zeros(HEADS, dtype=torch.double)
                torch.testing.assert_close(weights[b, i, :, m + 1], expected)
    _, weights_with_self = layer(x, NEIGHBORS_WITH_SELF, return_attention=True)
    assert weights_with_self[0, 0, :, 1].abs().max() == 0  # duplicate self entry is masked


def test_isolated_agent_attends_to_itself_only(layer, x):
    out = layer(x, NEIGHBORS)
    own_value = F.relu(layer.value(x[0, 4]))
    expected = F.relu(layer.output(own_value))
    assert torch.isfinite(out).all()
    torch.testing.assert_close(out[0, 4], expected)
    empty = torch.full((2, 5, 3), -1)
    torch.testing.assert_close(layer(x, empty), F.relu(layer.output(F.relu(layer.value(x)))))


def test_non_neighbours_have_no_influence(layer, x):
    out = layer(x, NEIGHBORS)
    changed = x.clone()
    changed[0, 3] += 5.0  # agent 3 of graph 0 is listed only by agent 2
    changed_out = layer(changed, NEIGHBORS)
    untouched = [0, 1, 4]
    torch.testing.assert_close(changed_out[0, untouched], out[0, untouched])
    assert not torch.allclose(changed_out[0, 2], out[0, 2])
    torch.testing.assert_close(changed_out[1], out[1])  # no leak into the other graph


def test_no_leak_across_graphs(layer, x):
    out = layer(x, NEIGHBORS)
    changed = x.clone()
    changed[1] = torch.randn(5, IN_DIM, dtype=torch.double)
    changed_out = layer(changed, NEIGHBORS)
    torch.testing.assert_close(changed_out[0], out[0])
    assert not torch.allclose(changed_out[1], out[1])


def test_mean_communication_matches_hand_mean(x):
    torch.manual_seed(0)
    layer = MeanCommunication(IN_DIM, OUT_DIM).double()
    mean = torch.zeros_like(x)
    for b in range(2):
        for i in range(5):
            others = [j for j in NEIGHBORS_WITH_SELF[b, i].tolist() if j >= 0 and j != i]
            if others:
                mean[b, i] = x[b, others].mean(0)
    expected = F.relu(layer.output(torch.cat([x, mean], dim=-1)))
    torch.testing.assert_close(layer(x, NEIGHBORS_WITH_SELF), expected)
    torch.testing.assert_close(layer(x, NEIGHBORS), expected)


def test_self_only_equals_attention_without_neighbours(layer, x):
    self_only = SelfOnly(IN_DIM, OUT_DIM, HEADS, HEAD_DIM).double()
    self_only.value.load_state_dict(layer.value.state_dict())
    self_only.output.load_state_dict(layer.output.state_dict())
    empty = torch.full((2, 5, 3), -1)
    torch.testing.assert_close(self_only(x, NEIGHBORS), layer(x, empty))


def inputs(net: HGRN, batch: int = 3, n_agents: int = 6, max_neighbors: int = 4):
    obs = torch.randn(batch, n_agents, net.obs_dim)
    neighbors = torch.randint(-1, n_agents, (batch, n_agents, max_neighbors))
    hidden = torch.randn(batch, n_agents, net.state_dim)
    return obs, neighbors, hidden


@pytest.mark.parametrize("communication", ["hgat", "mean", "none"])
@pytest.mark.parametrize("recurrent", [True, False])
@pytest.mark.parametrize("max_neighbors", [0, 4])
def test_hgrn_shapes(communication, recurrent, max_neighbors):
    net = HGRN(obs_dim=5, n_actions=4, hidden_dim=16, communication=communication, recurrent=recurrent)
    assert net.state_dim == (16 if recurrent else 0)
    out, hidden = net(*inputs(net, max_neighbors=max_neighbors))
    assert out.shape == (3, 6, 4)
    assert hidden.shape == (3, 6, net.state_dim)
    assert torch.isfinite(out).all()


def test_hgrn_hidden_state_matters():
    torch.manual_seed(0)
    net = HGRN(obs_dim=5, n_actions=4, hidden_dim=16)
    obs, neighbors, hidden = inputs(net)
    out, new_hidden = net(obs, neighbors, hidden)
    out_zero, _ = net(obs, neighbors, torch.zeros_like(hidden))
    assert not torch.allclose(out, out_zero)
    assert not torch.allclose(new_hidden, hidden)
    expected = net.gru(
        torch.cat(
            [net.encoder(obs), h1 := net.comm1(net.encoder(obs), neighbors), net.comm2(h1, neighbors)], dim=-1
        ).reshape(18, -1),
        hidden.reshape(18, -1),
    ).reshape(3, 6, 16)
    torch.testing.assert_close(new_hidden, expected)
    torch.testing.assert_close(out, net.head(expected))


def test_hgrn_sizes():
    net = HGRN(obs_dim=5, n_actions=4, hidden_dim=32, n_heads=4)
    assert net.comm1.query[0].out_features == 32
    paper = HGRN(obs_dim=5, n_actions=4, **PAPER_SIZE)
    assert paper.comm1.query[0].out_features == 1024
    assert paper.gru[0].input_size == 768 and paper.head[0].in_features == 256
    assert HGRN(obs_dim=5, n_actions=4, hidden_dim=32, recurrent=False).head[0].in_features == 96


@pytest.mark.parametrize("communication", ["hgat", "mean", "none"])
@pytest.mark.parametrize("recurrent", [True, False])
def test_hgrn_gradients_reach_all_parameters(communication, recurrent):
    torch.manual_seed(0)
    net = HGRN(obs_dim=5, n_actions=4, hidden_dim=16, communication=communication, recurrent=recurrent)
    out, hidden = net(*inputs(net, batch=4, n_agents=8))
    (out.square().sum() + hidden.sum()).backward()
    for name, param in net.named_parameters():
        assert param.grad is not None and param.grad.abs().sum() > 0, name


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"communication": "dense"}, "'dense'"),
        ({"group_n_actions": [3, 5]}, "group_n_actions"),
        ({"group_n_actions": [4, 0]}, "group_n_actions"),
        ({"hidden_dim": 0}, "hidden_dim"),
        ({"n_heads": -1}, "n_heads"),
        ({"head_dim": 0}, "head_dim"),
        ({"obs_dim": 0}, "obs_dim"),
        ({"n_actions": 0}, "n_actions"),
        ({"hidden_dim": 2, "n_heads": 4}, "head_dim"),  # 2 // 4 == 0
    ],
)
def test_hgrn_rejects_bad_config(kwargs, message):
    config = {"obs_dim": 5, "n_actions": 4, **kwargs}
    with pytest.raises(ValueError, match=message):
        HGRN(**config)


def test_hgrn_rejects_bad_inputs():
    net = HGRN(obs_dim=5, n_actions=4, hidden_dim=16)
    obs, neighbors, hidden = inputs(net)
    bad_calls = [
        (obs[..., :4], neighbors, hidden),
        (obs[:2], neighbors, hidden),
        (obs, neighbors[:, :5], hidden),
        (obs, neighbors[0], hidden),
        (obs, neighbors, hidden[:2]),
        (obs, neighbors, hidden[..., :8]),
        (obs, neighbors.float(), hidden),
        (obs, torch.full_like(neighbors, 6), hidden),
        (obs, torch.full_like(neighbors, -2), hidden),
    ]
    for args in bad_calls:
        with pytest.raises(ValueError):
            net(*args)
    net(obs, neighbors.to(torch.int32), hidden)  # any integer dtype is accepted


# --- heterogeneous groups ------------------------------------------------------------------------
# One graph of 4 agents: agents 0, 1 in group 0, agents 2, 3 in group 1.
# Agent 0 lists 1 and 2; agent 1 lists nobody; agent 2 lists 0 and 3; agent 3 lists 2.
GROUP_NEIGHBORS = torch.tensor([[[1, 2], [-1, -1], [0, 3], [2, -1]]])
GROUPS = torch.tensor([[0, 0, 1, 1]])


@pytest.fixture(params=[1, 2], ids=["1 head", "2 heads"])
def hetero_layer(request) -> GraphAttention:
    torch.manual_seed(0)
    return GraphAttention(IN_DIM, OUT_DIM, n_heads=request.param, head_dim=HEAD_DIM, n_groups=2).double()


def hand_hgat(layer: GraphAttention, x: torch.Tensor) -> torch.Tensor:
    """HGAT written out agent by agent: receiver-owned query, sender-owned key/value, one softmax
    per sender group over the listed neighbours (self included), zero message from a group without
    neighbours, then the receiver's ReLU(Linear) per sender group's message and one Linear over
    their concatenation in group order."""
    groups = GROUPS[0].tolist()
    heads = layer.n_heads
    attended = {0: [0, 1, 2], 1: [1], 2: [2, 0, 3], 3: [3, 2]}
    out = []
    for i in range(4):
        q = F.relu(layer.query[groups[i]](x[i])).reshape(heads, HEAD_DIM)
        messages = []
        for sender_group in (0, 1):
            senders = [j for j in attended[i] if groups[j] == sender_group]
            if not senders:
                messages.append(torch.zeros(heads * HEAD_DIM, dtype=x.dtype))
                continue
            keys = torch.stack(
                [F.relu(layer.key[sender_group](x[j])).reshape(heads, HEAD_DIM) for j in senders]
            )
            values = torch.stack(
                [F.relu(layer.value[sender_group](x[j])).reshape(heads, HEAD_DIM) for j in senders]
            )
            weights = torch.softmax((keys * q).sum(-1) / math.sqrt(HEAD_DIM), dim=0)  # (senders, heads)
            messages.append((weights.unsqueeze(-1) * values).sum(0).reshape(-1))
        receiver = layer.output[groups[i]]
        mapped = [F.relu(pair(message)) for pair, message in zip(receiver.per_sender, messages, strict=True)]
        out.append(receiver.combine(torch.cat(mapped)))
    return torch.stack(out)


def test_hgat_matches_hand_computed_two_group_example(hetero_layer):
    torch.manual_seed(2)
    x = torch.randn(1, 4, IN_DIM, dtype=torch.double)
    graph = GraphBatch(GROUP_NEIGHBORS, GROUPS, n_groups=2)
    out, weights = hetero_layer(x, graph, return_attention=True)
    torch.testing.assert_close(out[0], hand_hgat(hetero_layer, x[0]))
    # agent 0 attends {0, 1} in group 0 and {2} alone in group 1: weight 1 on agent 2 in every head
    torch.testing.assert_close(
        weights[0, 0, :, 0] + weights[0, 0, :, 1], torch.ones(hetero_layer.n_heads).double()
    )
    assert (weights[0, 0, :, 2] == 1.0).all()


def test_hgat_gives_zero_message_from_a_group_without_neighbours(hetero_layer):
    torch.manual_seed(3)
    x = torch.randn(1, 4, IN_DIM, dtype=torch.double)
    graph = GraphBatch(GROUP_NEIGHBORS, GROUPS, n_groups=2)
    query, key, value = hetero_layer.project(x, graph)
    heads = hetero_layer.n_heads
    messages, _ = NeighborAttention.apply(query, key, value, graph.pattern(heads), graph.segments(True))
    assert messages.shape == (4, 2, heads, HEAD_DIM)
    assert messages[1, 1].abs().max() == 0  # agent 1 (group 0) has no group-1 neighbour
    own_value = F.relu(hetero_layer.value[0](x[0, 1])).reshape(heads, HEAD_DIM)
    torch.testing.assert_close(messages[1, 0], own_value)  # it attends to itself only


def test_hgat_without_grad_matches_with_grad(hetero_layer):
    torch.manual_seed(3)
    x = torch.randn(1, 4, IN_DIM, dtype=torch.double)
    graph = GraphBatch(GROUP_NEIGHBORS, GROUPS, n_groups=2)
    with torch.inference_mode():
        out, weights = hetero_layer(x, graph, return_attention=True)
    expected, expected_weights = hetero_layer(x, graph, return_attention=True)
    assert expected.grad_fn is not None
    torch.testing.assert_close(out, expected.detach())
    torch.testing.assert_close(weights, expected_weights)


def test_attention_without_grad_skips_the_autograd_function(layer, x, monkeypatch):
    def refuse(*_args):
        raise AssertionError("the autograd function ran")

    monkeypatch.setattr(NeighborAttention, "apply", refuse)
    with torch.no_grad():
        layer(x, NEIGHBORS)
    with pytest.raises(AssertionError, match="the autograd function ran"):
        layer(x, NEIGHBORS)  # recording a gradient needs it


def test_hgat_gradients_match_hand_computed(hetero_layer):
    torch.manual_seed(4)
    x = torch.randn(1, 4, IN_DIM, dtype=torch.double, requires_grad=True)
    graph = GraphBatch(GROUP_NEIGHBORS, GROUPS, n_groups=2)
    weight = torch.randn(4, OUT_DIM, dtype=torch.double)
    params = [x, *hetero_layer.parameters()]
    grads = torch.autograd.grad((hetero_layer(x, graph)[0] * weight).sum(), params, allow_unused=True)
    expected = torch.autograd.grad((hand_hgat(hetero_layer, x[0]) * weight).sum(), params, allow_unused=True)
    for grad, expected_grad in zip(grads, expected, strict=True):
        if expected_grad is None:
            assert grad is None or grad.abs().max() == 0
        else:
            torch.testing.assert_close(grad, expected_grad)
    assert torch.autograd.gradcheck(lambda inp: hetero_layer(inp, graph), (x,))


def test_own_group_attention_ignores_other_groups():
    torch.manual_seed(0)
    layer = GraphAttention(IN_DIM, OUT_DIM, 1, HEAD_DIM, n_groups=2, across_groups=False).double()
    x = torch.randn(1, 4, IN_DIM, dtype=torch.double)
    graph = GraphBatch(GROUP_NEIGHBORS, GROUPS, n_groups=2)
    out = layer(x, graph)
    changed = x.clone()
    changed[0, 2] += 3.0  # group 1: listed by agent 0 (group 0) and agent 3 (group 1)
    changed_out = layer(changed, graph)
    torch.testing.assert_close(changed_out[0, :2], out[0, :2])
    assert not torch.allclose(changed_out[0, 3], out[0, 3])


@pytest.mark.parametrize("communication", ["hgat", "gat", "mean", "none"])
def test_grouped_hgrn_masks_the_actions_a_group_lacks(communication):
    torch.manual_seed(0)
    net = HGRN(obs_dim=5, n_actions=4, hidden_dim=8, communication=communication, group_n_actions=[4, 2])
    groups = GROUPS.repeat(3, 1)
    obs = torch.randn(3, 4, 5)
    hidden = torch.randn(3, 4, 8)
    out, new_hidden = net(obs, GROUP_NEIGHBORS.repeat(3, 1, 1), hidden, groups)
    assert out.shape == (3, 4, 4) and new_hidden.shape == (3, 4, 8)
    assert (out[:, 2:, 2:] == MASKED_OUTPUT).all() and (out[:, :2] > MASKED_OUTPUT / 2).all()
    assert (torch.softmax(out, dim=-1)[:, 2:, 2:] == 0).all()
    # each group has its own parameters: the head of group 1 drives only agents 2 and 3
    with torch.no_grad():
        net.head[1].bias.add_(1.0)
    shifted, _ = net(obs, GROUP_NEIGHBORS.repeat(3, 1, 1), hidden, groups)
    torch.testing.assert_close(shifted[:, :2], out[:, :2])
    torch.testing.assert_close(shifted[:, 2:, :2], out[:, 2:, :2] + 1.0)
    with pytest.raises(ValueError, match="groups"):
        net(obs, GROUP_NEIGHBORS.repeat(3, 1, 1), hidden)
    with pytest.raises(ValueError, match="group ids"):
        net(obs, GROUP_NEIGHBORS.repeat(3, 1, 1), hidden, torch.full_like(groups, 2))


def test_grouped_network_with_identical_copies_equals_the_plain_network():
    """Two groups with the same parameters, attending within their own group, compute what one
    group computes on a graph whose edges all stay within a group."""
    torch.manual_seed(0)
    plain = HGRN(obs_dim=5, n_actions=4, hidden_dim=8, communication="gat")
    grouped = HGRN(obs_dim=5, n_actions=4, hidden_dim=8, communication="gat", group_n_actions=[4, 4])
    plain_parameters = dict(plain.named_parameters())
    with torch.no_grad():
        for name, parameter in grouped.named_parameters():
            parameter.copy_(plain_parameters[name.replace(".members.1.", ".members.0.")])
    obs, hidden = torch.randn(2, 4, 5), torch.randn(2, 4, 8)
    within_groups = torch.tensor([[[1, -1], [0, -1], [3, -1], [2, -1]]]).repeat(2, 1, 1)
    expected, expected_hidden = plain(obs, within_groups, hidden)
    out, new_hidden = grouped(obs, within_groups, hidden, GROUPS.repeat(2, 1))
    torch.testing.assert_close(out, expected)
    torch.testing.assert_close(new_hidden, expected_hidden)
    # across groups, own-group attention ignores the edges between groups
    out_across, _ = grouped(obs, GROUP_NEIGHBORS.repeat(2, 1, 1), hidden, GROUPS.repeat(2, 1))
    expected_across, _ = plain(
        obs, torch.tensor([[[1, -1], [-1, -1], [3, -1], [2, -1]]]).repeat(2, 1, 1), hidden
    )
    torch.testing.assert_close(out_across, expected_across)


def test_lists_longer_than_the_graph_match_the_dense_reference():
    """A list with at least as many entries as the graph has agents (a tiny graph with a wide
    neighbour list) is shortened to its valid entries; weights still map to the original entries."""
    torch.manual_seed(0)
    layer = GraphAttention(IN_DIM, OUT_DIM, 4, HEAD_DIM).double()
    x = torch.randn(1, 3, IN_DIM, dtype=torch.double)
    neighbors = torch.full((1, 3, 16), -1)
    neighbors[0, 0, 9] = 2  # agent 0 lists agent 2 near the end of its list
    neighbors[0, 1, [0, 15]] = torch.tensor([1, 0])  # agent 1 lists itself, then agent 0 last
    expected, dense_weights = dense_attention(layer, x, dense_adjacency(neighbors))
    out, weights = layer(x, neighbors, return_attention=True)
    torch.testing.assert_close(out, expected)
    assert weights.shape == (1, 3, 4, 17)
    torch.testing.assert_close(weights[0, 0, :, 10], dense_weights[0, 0, :, 2])
    torch.testing.assert_close(weights[0, 1, :, 16], dense_weights[0, 1, :, 0])
    torch.testing.assert_close(weights.sum(-1), torch.ones(1, 3, 4, dtype=torch.double))


@pytest.mark.parametrize("communication", ["hgat", "mean"])
def test_mixed_precision_matches_float32_within_bfloat16_rounding(communication):
    torch.manual_seed(0)
    kwargs = dict(obs_dim=5, n_actions=4, hidden_dim=32, communication=communication, group_n_actions=[4, 2])
    exact, mixed = HGRN(**kwargs), HGRN(**kwargs, mixed_precision=True)
    mixed.load_state_dict(exact.state_dict())
    groups, neighbors = GROUPS.repeat(3, 1), GROUP_NEIGHBORS.repeat(3, 1, 1)
    obs, hidden = torch.randn(3, 4, 5), torch.randn(3, 4, 32)
    expected, expected_hidden = exact(obs, neighbors, hidden, groups)
    out, new_hidden = mixed(obs, neighbors, hidden, groups)
    assert out.dtype == new_hidden.dtype == torch.float32
    assert not torch.equal(out, expected)  # the products did run in bfloat16 (8-bit mantissa)
    torch.testing.assert_close(out, expected, atol=0.03, rtol=0.03)
    torch.testing.assert_close(new_hidden, expected_hidden, atol=0.03, rtol=0.03)
    assert (out[:, 2:, 2:] == MASKED_OUTPUT).all()  # masked actions stay exact

    out.sum().backward()
    for name, parameter in mixed.named_parameters():
        assert parameter.grad is not None and parameter.grad.dtype == torch.float32, name


# --- sparse attention: CSR invariants, dense references on random graphs, no host sync -----------
RANDOM_CASES = [(3, 6, 4), (2, 5, 9)]  # (batch, n_agents, list width); 9 is wider than the graph


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize(("batch", "n_agents", "width"), RANDOM_CASES)
@pytest.mark.parametrize("n_groups", [1, 2])
def test_attention_patterns_satisfy_the_csr_invariants(device, batch, n_agents, width, n_groups):
    """Every CSR tensor the attention builds has sorted, distinct columns in each row (checked by
    torch), the forward pattern and the transposed one (rows head by head) hold the same entries,
    and the entries are the distinct listed agents: the pattern is exact, not just well formed."""
    neighbors = random_lists(batch, n_agents, width, seed=n_agents).to(device)
    groups = torch.randint(0, n_groups, (batch, n_agents), device=device)
    graph = GraphBatch(neighbors, groups, n_groups)
    rows = batch * n_agents
    expected = dense_adjacency(neighbors.cpu())  # (batch, n_agents, n_agents)
    attended = torch.zeros(rows, rows + graph.targets.shape[1], dtype=torch.bool)
    attended.scatter_(1, graph.targets.cpu(), graph.mask.cpu())
    assert torch.equal(attended[:, :rows], torch.block_diag(*expected).reshape(rows, rows))
    assert not attended[:, rows:].any()  # dummy targets never take part
    for heads in (1, 3):
        pattern = graph.pattern(heads)
        values = torch.randn(pattern.col.numel(), dtype=torch.double, device=device)
        matrix = torch.sparse_csr_tensor(
            pattern.crow, pattern.col, values, pattern.shape, check_invariants=True
        )
        transposed = torch.sparse_csr_tensor(
            pattern.crow_t,
            pattern.col_t,
            values[pattern.transpose],
            pattern.shape[::-1],
            check_invariants=True,
        )
        by_head = matrix.to_dense().t().reshape(-1, heads, pattern.shape[0]).transpose(0, 1)
        torch.testing.assert_close(transposed.to_dense(), by_head.reshape(pattern.shape[::-1]))
    layer = GraphAttention(IN_DIM, OUT_DIM, 2, HEAD_DIM, n_groups=n_groups).double().to(device)
    x = torch.randn(batch, n_agents, IN_DIM, dtype=torch.double, device=device, requires_grad=True)
    with torch.sparse.check_sparse_tensor_invariants():  # every CSR tensor of forward and backward
        layer(x, graph).sum().backward()
    assert torch.isfinite(x.grad).all()


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize(("batch", "n_agents", "width"), RANDOM_CASES)
@pytest.mark.parametrize(("n_groups", "across_groups"), [(1, True), (2, True), (2, False)])
def test_attention_on_random_graphs_matches_the_dense_reference(
    device, batch, n_agents, width, n_groups, across_groups
):
    """Outputs, list-layout weights and the gradients of inputs and parameters equal a dense masked
    softmax over the ``n x n`` adjacency (lists as sets) on graphs with empty entries, self entries,
    repeated neighbours and an agent without neighbours."""
    torch.manual_seed(n_agents + 10 * n_groups)
    layer = GraphAttention(IN_DIM, OUT_DIM, 2, HEAD_DIM, n_groups, across_groups).double().to(device)
    neighbors = random_lists(batch, n_agents, width, seed=batch).to(device)
    groups = torch.randint(0, n_groups, (batch, n_agents), device=device)
    x = torch.randn(batch, n_agents, IN_DIM, dtype=torch.double, device=device, requires_grad=True)
    weight = torch.randn(batch, n_agents, OUT_DIM, dtype=torch.double, device=device)
    params = [x, *layer.parameters()]

    out, weights = layer(x, GraphBatch(neighbors, groups, n_groups), return_attention=True)
    grads = torch.autograd.grad((out * weight).sum(), params, allow_unused=True)
    expected, dense_weights = dense_attention(layer, x, dense_adjacency(neighbors.cpu()).to(device), groups)
    expected_grads = torch.autograd.grad((expected * weight).sum(), params, allow_unused=True)

    torch.testing.assert_close(out, expected)
    torch.testing.assert_close(weights, dense_list_weights(dense_weights, neighbors.cpu()))
    for grad, expected_grad in zip(grads, expected_grads, strict=True):
        if expected_grad is None:  # a group's key/value that no agent attends to
            assert grad is None or grad.abs().max() == 0
        else:
            torch.testing.assert_close(grad, expected_grad)


def test_attention_gradcheck_on_a_random_two_group_graph():
    torch.manual_seed(0)
    layer = GraphAttention(IN_DIM, OUT_DIM, 2, HEAD_DIM, n_groups=2).double()
    graph = GraphBatch(random_lists(2, 5, 9, seed=1), torch.tensor([[0, 1, 0, 1, 1], [1, 1, 0, 0, 0]]), 2)
    x = torch.randn(2, 5, IN_DIM, dtype=torch.double, requires_grad=True)
    assert torch.autograd.gradcheck(lambda inp: layer(inp, graph), (x,))


def test_a_repeated_neighbour_counts_once():
    torch.manual_seed(0)
    layer = GraphAttention(IN_DIM, OUT_DIM, HEADS, HEAD_DIM).double()
    x = torch.randn(1, 4, IN_DIM, dtype=torch.double)
    once, once_weights = layer(x, torch.tensor([[[1, 2, -1, -1]] * 4]), return_attention=True)
    twice, twice_weights = layer(x, torch.tensor([[[1, 2, 1, 2]] * 4]), return_attention=True)
    torch.testing.assert_close(twice, once)
    torch.testing.assert_close(twice_weights, once_weights)  # the repeats carry weight 0
    mean = MeanCommunication(IN_DIM, OUT_DIM).double()
    torch.testing.assert_close(
        mean(x, torch.tensor([[[1, 2, 1, 2]] * 4])), mean(x, torch.tensor([[[1, 2]] * 4]))
    )


class _HostSyncRecorder(TorchDispatchMode):
    """Records the ops that read tensor values on the host (a device synchronisation on CUDA),
    except those of the CPU-only value check in ``check_neighbors``."""

    SYNCING = {"aten::_local_scalar_dense", "aten::nonzero", "aten::bincount", "aten::masked_select",
               "aten::_unique2", "aten::unique_consecutive", "aten::unique_dim", "aten::is_nonzero",
               "aten::equal", "aten::allclose"}  # fmt: skip

    def __init__(self) -> None:
        super().__init__()
        self.syncing: list[str] = []

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        name = func._schema.name
        indices = args[1] if name in ("aten::index", "aten::index_put", "aten::index_put_") else []
        bool_index = any(index is not None and index.dtype == torch.bool for index in indices)
        unsized = (
            func is torch.ops.aten.repeat_interleave.Tensor and (kwargs or {}).get("output_size") is None
        )
        if name in self.SYNCING or bool_index or unsized:
            if "check_neighbors" not in {frame.name for frame in traceback.extract_stack()}:
                self.syncing.append(str(func))
        return func(*args, **(kwargs or {}))


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("communication", ["hgat", "mean"])
def test_homogeneous_forward_and_backward_do_not_read_values_on_the_host(device, communication):
    torch.manual_seed(0)
    net = HGRN(obs_dim=5, n_actions=4, hidden_dim=16, communication=communication).to(device)
    obs, neighbors, hidden = (tensor.to(device) for tensor in inputs(net, max_neighbors=9))
    if device == "cpu":
        recorder = _HostSyncRecorder()
        with recorder:
            out, new_hidden = net(obs, GraphBatch(neighbors), hidden)
            (out.sum() + new_hidden.sum()).backward()
        assert recorder.syncing == []
    else:
        torch.cuda.set_sync_debug_mode("error")  # raises on a synchronising CUDA call
        try:
            out, new_hidden = net(obs, GraphBatch(neighbors), hidden)
            (out.sum() + new_hidden.sum()).backward()
        finally:
            torch.cuda.set_sync_debug_mode("default")


def test_the_recorder_sees_host_reads():
    recorder = _HostSyncRecorder()
    with recorder:
        tensor = torch.arange(4)
        int(tensor.max())
        tensor[tensor > 1].nonzero()
        torch.repeat_interleave(tensor)
        torch.repeat_interleave(tensor, output_size=6)  # sized: no host read
    assert recorder.syncing == [
        "aten._local_scalar_dense.default",
        "aten.index.Tensor",
        "aten.nonzero.default",
        "aten.repeat_interleave.Tensor",
    ]


def test_one_graph_batch_serves_networks_of_any_head_count():
    torch.manual_seed(0)
    nets = [HGRN(obs_dim=5, n_actions=4, hidden_dim=16, n_heads=heads) for heads in (1, 2, 4)]
    nets.append(HGRN(obs_dim=5, n_actions=4, hidden_dim=16, communication="mean"))
    obs, neighbors, hidden = inputs(nets[0], max_neighbors=5)
    graph = GraphBatch(neighbors)
    for net in [*nets, *nets]:  # every network twice, in turn
        for shared, alone in zip(net(obs, graph, hidden), net(obs, neighbors, hidden), strict=True):
            torch.testing.assert_close(shared, alone)
    assert sorted(graph._patterns) == [1, 2, 4]


def test_the_transposed_pattern_is_built_for_gradients_only():
    """Acting and target networks (no gradient) never pay for the transposed pattern; a backward
    pass builds it once and every later one reuses it."""
    torch.manual_seed(0)
    net = HGRN(obs_dim=5, n_actions=4, hidden_dim=16)
    obs, neighbors, hidden = inputs(net, max_neighbors=5)
    graph = GraphBatch(neighbors)
    with torch.no_grad():
        net(obs, graph, hidden)
    pattern = graph.pattern(4)
    assert "_transposed" not in vars(pattern)
    net(obs, graph, hidden)[0].sum().backward()
    built = vars(pattern)["_transposed"]
    net(obs, graph, hidden)[0].sum().backward()
    assert vars(pattern)["_transposed"] is built


def test_hgrn_rejects_a_graph_batch_that_does_not_fit():
    net = HGRN(obs_dim=5, n_actions=4, hidden_dim=8, group_n_actions=[4, 2])
    obs, hidden, groups = torch.randn(3, 4, 5), torch.randn(3, 4, 8), GROUPS.repeat(3, 1)
    neighbors = GROUP_NEIGHBORS.repeat(3, 1, 1)
    graph = GraphBatch(neighbors, groups, n_groups=2)
    expected = net(obs, neighbors, hidden, groups)
    for shared, alone in zip(net(obs, graph, hidden), expected, strict=True):
        torch.testing.assert_close(shared, alone)
    with pytest.raises(ValueError, match="n_groups=2"):
        net(obs, graph, hidden, groups)  # the groups are in the graph batch already
    with pytest.raises(ValueError, match="n_groups=2"):
        net(obs, GraphBatch(neighbors), hidden)
    with pytest.raises(ValueError, match="GraphBatch holds"):
        net(obs[:2], graph, hidden[:2])


@pytest.mark.parametrize("algorithm", ["soft", "sac"])
def test_acting_builds_one_graph_batch_for_all_networks(monkeypatch, algorithm):
    from sb3_hgrn import SACHGRN, SoftHGRN, make_graph_vec_env

    env = make_graph_vec_env("ctc_v0", env_kwargs=dict(n_hunters=3, n_red_banks=1, n_blue_banks=1))
    policy_kwargs = dict(hidden_dim=8)
    if algorithm == "sac":  # two critics with another head count than the actor's
        policy_kwargs.update(n_critics=2, critic_kwargs=dict(n_heads=2))
    model = (SACHGRN if algorithm == "sac" else SoftHGRN)("GraphPolicy", env, policy_kwargs=policy_kwargs)
    built = []
    original = GraphBatch.__init__
    monkeypatch.setattr(GraphBatch, "__init__", lambda self, *args: built.append(original(self, *args)))
    model.predict(env.reset())
    assert len(built) == 1


@pytest.mark.parametrize("recurrent", [True, False])
@pytest.mark.parametrize("group_n_actions", [None, [4, 3, 2]])
def test_unroll_equals_stepping_the_network_one_step_at_a_time(recurrent, group_n_actions):
    """:func:`unroll` runs the layers before the memory once over all steps' graphs; its outputs and
    their gradients equal those of calling the network step by step on each step's own graphs, with
    the state carried along and reset where an episode starts."""
    torch.manual_seed(0)
    n_steps, batch, n_agents = 3, 2, 5
    n_groups = 1 if group_n_actions is None else len(group_n_actions)
    net = HGRN(6, 4, hidden_dim=8, n_heads=2, recurrent=recurrent, group_n_actions=group_n_actions)
    obs = torch.randn(n_steps * batch, n_agents, 6)
    neighbors = torch.randint(-1, n_agents, (n_steps * batch, n_agents, 3))
    groups = None if n_groups == 1 else torch.randint(0, n_groups, (n_steps * batch, n_agents))
    starts = [torch.tensor([False, False]), torch.tensor([True, False]), torch.tensor([False, True])]
    state = torch.randn(batch, n_agents, net.state_dim)
    weights = torch.randn(n_steps * batch, n_agents, 4)

    def loss_and_gradients(outputs: torch.Tensor) -> tuple[torch.Tensor, ...]:
        valid = outputs > MASKED_OUTPUT
        return outputs, *torch.autograd.grad((outputs * weights * valid).sum(), list(net.parameters()))

    unrolled = unroll(net, obs, GraphBatch(neighbors, groups, n_groups), state, starts)
    stepped, carried = [], state
    for index, step_starts in enumerate(starts):
        rows = slice(index * batch, (index + 1) * batch)
        if index > 0:
            carried = carried * (~step_starts).to(carried.dtype)[:, None, None]
        step_groups = None if groups is None else groups[rows]
        output, carried = net(obs[rows], GraphBatch(neighbors[rows], step_groups, n_groups), carried)
        stepped.append(output)
    expected = loss_and_gradients(torch.cat(stepped))
    for ours, theirs in zip(loss_and_gradients(unrolled), expected, strict=True):
        torch.testing.assert_close(ours, theirs, atol=1e-5, rtol=1e-5)


COMPILE_FOR_TESTS = {"backend": "aot_eager"}
"""``torch.compile`` traced into one graph and run without code generation: what the library's
compiled path decides (the gathered attention, the graph capture) without a C++ compiler's time."""


@pytest.mark.parametrize(
    "communication, group_n_actions, mixed_precision",
    [
        ("hgat", None, False),
        ("hgat", [4, 2, 3], False),
        ("gat", [4, 2], False),
        ("mean", [4, 3], False),
        ("none", None, False),
        ("hgat", [4, 2], True),
    ],
)
def test_the_compiled_network_equals_the_eager_one(communication, group_n_actions, mixed_precision):
    """``compile_network`` (the attention gathered, under ``torch.compile``) gives the eager network's
    outputs, states and parameter gradients, with one and several agent groups, an agent without a
    neighbour of some group, repeated and empty list entries."""
    torch.manual_seed(0)
    kwargs = dict(hidden_dim=8, n_heads=2, group_n_actions=group_n_actions, mixed_precision=mixed_precision)
    traced = []

    def backend(graph_module, example_inputs):
        traced.append(graph_module)
        return torch._dynamo.lookup_backend(COMPILE_FOR_TESTS["backend"])(graph_module, example_inputs)

    eager = HGRN(6, 4, communication=communication, **kwargs)
    compiled = HGRN(6, 4, communication=communication, compile_network={"backend": backend}, **kwargs)
    compiled.load_state_dict(eager.state_dict())
    n_groups = eager.n_groups
    obs, hidden = torch.randn(3, 7, 6), torch.randn(3, 7, 8)
    neighbors = torch.randint(-1, 7, (3, 7, 4))
    neighbors[0, 0] = -1
    neighbors[0, 1, :2] = 2
    groups = None if n_groups == 1 else torch.randint(0, n_groups, (3, 7))
    weights = torch.randn(3, 7, 4)
    results = []
    for net in (eager, compiled):
        outputs, state = net(obs, GraphBatch(neighbors, groups, n_groups), hidden)
        valid = outputs > MASKED_OUTPUT
        loss = (outputs * weights * valid).sum() + state.sum()
        results.append([outputs, state, *torch.autograd.grad(loss, list(net.parameters()))])
    assert traced, "the compiled network ran eagerly"
    tolerance = dict(atol=2e-2, rtol=2e-2) if mixed_precision else dict(atol=1e-5, rtol=1e-5)
    for ours, theirs in zip(results[1], results[0], strict=True):
        torch.testing.assert_close(ours, theirs, **tolerance)


def test_compiled_networks_each_run_with_their_own_parameters():
    """Networks of one shape share the compiled code, not its parameters: each gives what its eager
    twin gives, acting (no gradient) and training."""
    nets = []
    for seed in (0, 1):
        torch.manual_seed(seed)
        eager = HGRN(6, 4, hidden_dim=8, n_heads=2)
        compiled = HGRN(6, 4, hidden_dim=8, n_heads=2, compile_network=COMPILE_FOR_TESTS)
        compiled.load_state_dict(eager.state_dict())
        nets.append((eager, compiled))
    obs, hidden, neighbors = torch.randn(2, 5, 6), torch.zeros(2, 5, 8), torch.randint(-1, 5, (2, 5, 3))
    for grad in (False, True):
        with torch.set_grad_enabled(grad):
            for eager, compiled in nets:
                torch.testing.assert_close(
                    compiled(obs, neighbors, hidden)[0], eager(obs, neighbors, hidden)[0]
                )
    assert not torch.allclose(nets[0][0](obs, neighbors, hidden)[0], nets[1][0](obs, neighbors, hidden)[0])


@pytest.mark.parametrize("value", [1, "yes", {3: "x"}])
def test_compile_network_rejects_what_torch_compile_does_not_take(value):
    with pytest.raises(ValueError, match="compile_network must be True, False or a dict"):
        HGRN(6, 4, compile_network=value)


def test_a_network_that_cannot_compile_says_why():
    def broken_backend(graph_module, example_inputs):
        raise OSError("no C++ compiler found")

    net = HGRN(6, 4, hidden_dim=8, n_heads=2, compile_network={"backend": broken_backend})
    with pytest.raises(RuntimeError, match="could not compile the network: OSError.*no C\\+\\+ compiler"):
        net(torch.randn(1, 3, 6), torch.randint(-1, 3, (1, 3, 2)), torch.zeros(1, 3, 8))
