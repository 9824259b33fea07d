"""Tests of the HGRN network and its communication layers against dense hand-written references."""

import math

import pytest
import torch
import torch.nn.functional as F

from sb3_hgrn.common.hgrn import HGRN, PAPER_SIZE, GraphAttention, MeanCommunication, SelfOnly

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


def dense_attention(layer: GraphAttention, x: torch.Tensor, adjacency: torch.Tensor):
    """Reference output ``(batch, n, out)`` and weights ``(batch, n, heads, n)`` with dense softmax."""
    batch, n, _ = x.shape
    heads, dim = layer.n_heads, layer.head_dim
    q, k, v = (F.relu(lin(x)).reshape(batch, n, heads, dim) for lin in (layer.query, layer.key, layer.value))
    logits = torch.einsum("bihd,bjhd->bihj", q, k) / math.sqrt(dim)
    logits = logits.masked_fill(~adjacency.unsqueeze(2), -math.inf)
    weights = logits.softmax(dim=-1)
    mixed = torch.einsum("bihj,bjhd->bihd", weights, v).reshape(batch, n, heads * dim)
    return F.relu(layer.output(mixed)), weights


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
    assert net.comm1.query.out_features == 32
    paper = HGRN(obs_dim=5, n_actions=4, **PAPER_SIZE)
    assert paper.comm1.query.out_features == 1024
    assert paper.gru.input_size == 768 and paper.head.in_features == 256
    assert HGRN(obs_dim=5, n_actions=4, hidden_dim=32, recurrent=False).head.in_features == 96


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
        ({"communication": "gat"}, "'gat'"),
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
