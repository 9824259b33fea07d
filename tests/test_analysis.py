"""Analysis helpers: GRU gates, the recorded forward pass, attention weights and episode records."""

import numpy as np
import pytest
import torch
from torch import nn

from sb3_hgrn import SACHGRN, SoftHGRN, make_graph_vec_env
from sb3_hgrn.analysis import attention_by_agent, forward_with_internals, gru_gates, record_episode
from sb3_hgrn.common.hgrn import HGRN

SMALL = {"hidden_dim": 16, "n_heads": 2}


def random_graphs(batch: int, n_agents: int, max_neighbors: int, seed: int = 0) -> torch.Tensor:
    """``(batch, n_agents, max_neighbors)`` random neighbour lists with empty entries and self entries."""
    generator = torch.Generator().manual_seed(seed)
    return torch.randint(-1, n_agents, (batch, n_agents, max_neighbors), generator=generator)


@pytest.mark.parametrize("bias", [True, False])
def test_gru_gates_rebuild_the_cell_output(bias: bool) -> None:
    torch.manual_seed(0)
    cell = nn.GRUCell(5, 4, bias=bias)
    x, h = torch.randn(7, 5), torch.randn(7, 4)
    reset, update = gru_gates(cell, x, h)
    assert reset.shape == update.shape == (7, 4)
    candidate = torch.tanh(
        nn.functional.linear(x, cell.weight_ih[8:], None if cell.bias_ih is None else cell.bias_ih[8:])
        + reset
        * nn.functional.linear(h, cell.weight_hh[8:], None if cell.bias_hh is None else cell.bias_hh[8:])
    )
    torch.testing.assert_close((1 - update) * candidate + update * h, cell(x, h))


@pytest.mark.parametrize("group_n_actions", [None, [3, 5]])
def test_recorded_forward_reproduces_the_network(group_n_actions: list[int] | None) -> None:
    torch.manual_seed(0)
    batch, n_agents, n_neighbors = 3, 6, 4
    network = HGRN(obs_dim=7, n_actions=5, hidden_dim=16, n_heads=2, group_n_actions=group_n_actions)
    obs, hidden = torch.randn(batch, n_agents, 7), torch.randn(batch, n_agents, 16)
    neighbors = random_graphs(batch, n_agents, n_neighbors)
    groups = None if group_n_actions is None else torch.randint(0, 2, (batch, n_agents))
    internals = forward_with_internals(network, obs, neighbors, hidden, groups)
    out, new_hidden = network(obs, neighbors, hidden, groups)
    torch.testing.assert_close(internals.out, out)
    torch.testing.assert_close(internals.hidden, new_hidden)
    for attention in (internals.attention1, internals.attention2):
        assert attention.shape == (batch, n_agents, 2, n_neighbors + 1)
    assert internals.reset.shape == internals.update.shape == (batch, n_agents, 16)
    assert ((internals.reset > 0) & (internals.reset < 1)).all()


def test_attention_weights_sum_to_one_over_attended_entries() -> None:
    torch.manual_seed(0)
    network = HGRN(obs_dim=7, n_actions=5, hidden_dim=16, n_heads=2)
    neighbors = random_graphs(2, 6, 4, seed=1)
    internals = forward_with_internals(network, torch.randn(2, 6, 7), neighbors, torch.zeros(2, 6, 16))
    own = torch.arange(6).view(1, 6, 1)
    attended = torch.cat([torch.ones(2, 6, 1, dtype=torch.bool), (neighbors >= 0) & (neighbors != own)], -1)
    for attention in (internals.attention1, internals.attention2):
        torch.testing.assert_close(attention.sum(-1), torch.ones(2, 6, 2))
        assert (attention[~attended.unsqueeze(2).expand_as(attention)] == 0).all()


def test_forward_with_internals_needs_attention_and_a_gru() -> None:
    x = (torch.zeros(1, 3, 7), torch.full((1, 3, 2), -1), torch.zeros(1, 3, 16))
    with pytest.raises(ValueError, match="graph attention"):
        forward_with_internals(HGRN(7, 5, hidden_dim=16, communication="mean"), *x)
    with pytest.raises(ValueError, match="recurrent"):
        forward_with_internals(HGRN(7, 5, hidden_dim=16, recurrent=False), *x[:2], torch.zeros(1, 3, 0))


def test_attention_by_agent_maps_list_entries_to_agents() -> None:
    weights = np.array([[0.5, 0.0, 0.3, 0.2, 0.0], [1.0, 0.0, 0.0, 0.0, 0.0]])  # column 0 = itself
    neighbors = np.array([[1, 2, 3, -1], [1, -1, -1, -1]])  # agent 1 itself first, as the envs list it
    np.testing.assert_allclose(
        attention_by_agent(weights, neighbors, agent=1, n_agents=4), [[0, 0.5, 0.3, 0.2], [0, 1, 0, 0]]
    )


def surviving_env(n_agents: int = 5):
    # short lists: hgrn's sparse attention needs n_agents * n_heads >= max_neighbors + 1 in one graph
    env_kwargs = {"n_agents": n_agents, "map_size": 8, "n_resources": 1, "max_cycles": 4, "max_neighbors": 4}
    return make_graph_vec_env("surviving_v0", seed=0, env_kwargs=env_kwargs)


def test_record_episode_threads_the_state_and_records_shapes() -> None:
    env = surviving_env()
    model = SoftHGRN("GraphPolicy", env, policy_kwargs=SMALL, seed=0)
    n_steps, n_neighbors = 6, env.max_neighbors  # runs past the end of the 4-step episode
    record = record_episode(model, env, n_steps, agent=2, deterministic=True)
    assert record.attention1.shape == record.attention2.shape == (n_steps, n_neighbors + 1)
    np.testing.assert_allclose(record.attention1.sum(-1), 1.0, rtol=1e-5)
    np.testing.assert_allclose(record.attention2.sum(-1), 1.0, rtol=1e-5)
    assert record.neighbors.shape == (n_steps, n_neighbors) and (record.neighbors[:, 0] == 2).all()
    assert record.reset_gate.shape == record.reset_gate_all.shape == (n_steps,)
    assert record.cells.shape == (n_steps, 5, 2)
    # greedy actions come from the recorded outputs only if the recorded state is the model's
    np.testing.assert_array_equal(record.actions, record.outputs.argmax(-1))


def test_record_episode_follows_scripted_actions_with_sac_hgrn() -> None:
    env = surviving_env(n_agents=3)
    model = SACHGRN("GraphPolicy", env, policy_kwargs=SMALL, seed=0)
    scripted = np.full((3, 3), -1)
    scripted[:, 0] = [3, 3, 1]
    record = record_episode(model, env, 3, scripted_actions=scripted, deterministic=True)
    np.testing.assert_array_equal(record.actions[:, 0], [3, 3, 1])
    np.testing.assert_array_equal(record.actions[:, 1:], record.outputs[:, 1:].argmax(-1))
    with pytest.raises(ValueError, match="one-copy"):
        record_episode(model, make_graph_vec_env("surviving_v0", n_envs=2, env_kwargs={"n_agents": 3}), 3)
