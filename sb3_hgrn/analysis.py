"""Look inside a trained HGRN, step by step: attention weights and GRU gates (the paper's case study).

:func:`forward_with_internals` runs an :class:`~sb3_hgrn.common.hgrn.HGRN` with its own submodules
(encoder, both attention layers, GRU, head) and keeps what the plain forward pass discards: the
attention weights of both layers and the GRU's reset and update gates (``nn.GRUCell`` does not expose
them; :func:`gru_gates` recomputes them from its weights). :func:`record_episode` threads a model's
recurrent state through an episode and records one agent's view of it.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
import torch
import torch.nn.functional as F
from stable_baselines3.common.vec_env import VecEnv
from torch import Tensor, nn

from sb3_hgrn.common.attention import GraphBatch
from sb3_hgrn.common.hgrn import HGRN, MASKED_OUTPUT, GraphAttention
from sb3_hgrn.common.off_policy import GraphOffPolicyAlgorithm


def gru_gates(cell: nn.GRUCell, x: Tensor, h: Tensor) -> tuple[Tensor, Tensor]:
    """Reset and update gates of a GRUCell.

    With PyTorch's gate order (r, z, n) in ``weight_ih`` and ``weight_hh``:
    ``r = sigmoid(W_ir x + b_ir + W_hr h + b_hr)``, ``z = sigmoid(W_iz x + b_iz + W_hz h + b_hz)``; the
    cell's output is ``(1 - z) * n + z * h`` with ``n = tanh(W_in x + b_in + r * (W_hn h + b_hn))``.

    :param cell: the GRU cell.
    :param x: ``(rows, input_size)`` inputs.
    :param h: ``(rows, hidden_size)`` states fed in.
    :return: reset gate ``r`` and update gate ``z``, ``(rows, hidden_size)`` each.
    """
    input_reset, input_update, _ = F.linear(x, cell.weight_ih, cell.bias_ih).chunk(3, dim=-1)
    hidden_reset, hidden_update, _ = F.linear(h, cell.weight_hh, cell.bias_hh).chunk(3, dim=-1)
    return torch.sigmoid(input_reset + hidden_reset), torch.sigmoid(input_update + hidden_update)


@dataclass
class Internals:
    """One forward pass of an HGRN with its intermediate results (``K`` = ``max_neighbors``).

    :ivar out: ``(batch, n_agents, n_actions)`` outputs, as the network's own forward pass gives them.
    :ivar hidden: ``(batch, n_agents, hidden_dim)`` new recurrent state.
    :ivar attention1: ``(batch, n_agents, n_heads, K + 1)`` weights of the first attention layer;
        column 0 is the agent itself, column ``1 + m`` its list entry ``m``.
    :ivar attention2: the same for the second layer.
    :ivar reset: ``(batch, n_agents, hidden_dim)`` reset gate of the GRU.
    :ivar update: ``(batch, n_agents, hidden_dim)`` update gate of the GRU.
    """

    out: Tensor
    hidden: Tensor
    attention1: Tensor
    attention2: Tensor
    reset: Tensor
    update: Tensor


def forward_with_internals(
    network: HGRN, obs: Tensor, neighbors: Tensor, hidden: Tensor, groups: Tensor | None = None
) -> Internals:
    """Run ``network`` like its ``forward`` and keep attention weights and gates.

    The network needs graph attention (``communication`` ``"hgat"`` or ``"gat"``) and its GRU.

    :param network: the HGRN.
    :param obs: ``(batch, n_agents, *obs_shape)`` float observations.
    :param neighbors: ``(batch, n_agents, K)`` agent indices, ``-1`` = no entry.
    :param hidden: ``(batch, n_agents, hidden_dim)`` recurrent state fed in.
    :param groups: ``(batch, n_agents)`` group ids (needed with several groups).
    """
    if not (isinstance(network.comm1, GraphAttention) and isinstance(network.comm2, GraphAttention)):
        raise ValueError("forward_with_internals needs a network with graph attention ('hgat' or 'gat').")
    if network.gru is None:
        raise ValueError("forward_with_internals needs a recurrent network (a GRU).")
    batch, n_agents = obs.shape[:2]
    graph = GraphBatch(neighbors, groups, network.n_groups)
    encoded = network.encode(obs, graph)
    hop1, attention1 = network.comm1(encoded, graph, return_attention=True)
    hop2, attention2 = network.comm2(hop1, graph, return_attention=True)
    x = torch.cat([encoded, hop1, hop2], dim=-1).reshape(batch * n_agents, -1)
    h = hidden.reshape(batch * n_agents, -1)
    new_hidden = network.gru(x, h, graph=graph)
    reset, update = torch.empty_like(h), torch.empty_like(h)
    group_rows = graph.group_rows or [torch.arange(batch * n_agents, device=obs.device)]
    for cell, rows in zip(network.gru.members, group_rows, strict=True):
        reset[rows], update[rows] = gru_gates(cell, x[rows], h[rows])
    new_hidden = new_hidden.reshape(batch, n_agents, -1)
    out = network.head(new_hidden, graph=graph)
    if network.n_groups > 1:
        out = out.masked_fill(~network.valid_actions[graph.row_groups].reshape(out.shape), MASKED_OUTPUT)
    shape = (batch, n_agents, -1)
    return Internals(out, new_hidden, attention1, attention2, reset.reshape(shape), update.reshape(shape))


@dataclass
class EpisodeRecord:
    """What one agent's network did at every step of an episode (``T`` steps, ``N`` agents).

    :ivar attention1: ``(T, K + 1)`` the agent's weights in the first attention layer, heads averaged;
        column 0 is the agent itself, column ``1 + m`` its list entry ``neighbors[t, m]``.
    :ivar attention2: ``(T, K + 1)`` the same for the second layer.
    :ivar neighbors: ``(T, K)`` the agent's neighbour list (``-1`` = no entry).
    :ivar reset_gate: ``(T,)`` mean of the agent's reset gate over the hidden units.
    :ivar reset_gate_all: ``(T,)`` mean reset gate over all agents and hidden units.
    :ivar outputs: ``(T, N, n_actions)`` outputs of the recorded network (Q-values or logits).
    :ivar actions: ``(T, N)`` actions taken.
    :ivar cells: ``(T, N, 2)`` agent cells before each step, if the env has ``agent_cells()``
        (Surviving), else None.
    """

    attention1: np.ndarray
    attention2: np.ndarray
    neighbors: np.ndarray
    reset_gate: np.ndarray
    reset_gate_all: np.ndarray
    outputs: np.ndarray
    actions: np.ndarray
    cells: np.ndarray | None


def attention_by_agent(weights: np.ndarray, neighbors: np.ndarray, agent: int, n_agents: int) -> np.ndarray:
    """Attention weights per agent index instead of per neighbour-list entry.

    :param weights: ``(T, K + 1)`` weights of ``agent``: column 0 itself, column ``1 + m`` entry ``m``.
    :param neighbors: ``(T, K)`` its neighbour lists (``-1`` = no entry).
    :param agent: the attending agent.
    :param n_agents: number of agents.
    :return: ``(T, n_agents)``: column ``j`` is the weight on agent ``j`` (0 where it is not listed).
    """
    by_agent = np.zeros((len(weights), n_agents))
    by_agent[:, agent] = weights[:, 0]
    listed = (neighbors >= 0) & (neighbors != agent)  # other entries carry weight 0
    steps = np.broadcast_to(np.arange(len(weights))[:, None], neighbors.shape)
    np.add.at(by_agent, (steps[listed], neighbors[listed]), weights[:, 1:][listed])
    return by_agent


def record_episode(
    model: GraphOffPolicyAlgorithm,
    env: VecEnv,
    n_steps: int,
    agent: int = 0,
    scripted_actions: np.ndarray | None = None,
    deterministic: bool = False,
) -> EpisodeRecord:
    """Run ``model`` on a one-copy graph VecEnv for ``n_steps`` steps and record ``agent``'s internals.

    The recorded network is the model's online acting network (``policy.online_network``): the
    Q-network of SoftHGRN, the actor of SACHGRN, or its first critic when the critic's Boltzmann
    policy acts (``behaviour_policy="critic"``, the default). The env is reset first; the model's
    recurrent state is threaded from step to step (and zeroed when an episode ends) as in ``predict``.

    :param model: a SoftHGRN or SACHGRN model whose policy knows the env's agent count (built on
        ``env``, or loaded onto it with ``SoftHGRN.load(path, env=env)``).
    :param env: graph VecEnv with one copy (``num_envs == n_agents``).
    :param n_steps: steps to record.
    :param agent: the agent whose attention is recorded.
    :param scripted_actions: ``(n_steps, n_agents)`` actions to take instead of the model's, ``-1``
        where the model acts.
    :param deterministic: greedy actions instead of sampled ones.
    """
    policy = model.policy
    n_agents = env.num_envs
    if getattr(env, "n_agents", None) != n_agents or policy.n_agents != n_agents:
        raise ValueError(
            "record_episode needs a one-copy graph VecEnv whose agent count the model's policy knows "
            "(load the model onto it with SoftHGRN.load(path, env=env))."
        )
    if n_steps < 1:
        raise ValueError(f"n_steps must be >= 1, got {n_steps}.")
    if scripted_actions is not None and np.shape(scripted_actions) != (n_steps, n_agents):
        raise ValueError(f"scripted_actions must have shape {(n_steps, n_agents)}.")
    network = policy.online_network
    place = next(i for i, carried in enumerate(policy.recurrent_networks) if carried is network)
    copy = env.envs[0] if hasattr(env, "envs") else None
    has_cells = callable(getattr(copy, "agent_cells", None))
    columns: dict[str, list[np.ndarray]] = {field.name: [] for field in fields(EpisodeRecord)}
    policy.set_training_mode(False)
    observations = env.reset()
    state = np.zeros((1, n_agents, policy.state_dim), dtype=np.float32)
    with torch.no_grad():
        for step in range(n_steps):
            obs, neighbors, groups = policy.to_graphs(policy.obs_to_tensor(observations)[0])
            own_state = policy.split_state(torch.as_tensor(state, device=policy.device))[place]
            internals = forward_with_internals(network, obs, neighbors, own_state, groups)
            if has_cells:
                columns["cells"].append(copy.agent_cells())
            actions, (state,) = model.predict(observations, state=(state,), deterministic=deterministic)
            if scripted_actions is not None:
                actions = np.where(scripted_actions[step] >= 0, scripted_actions[step], actions)
            observations, _, dones, _ = env.step(actions)
            state = state * (1.0 - dones.astype(np.float32))[None, :, None]
            columns["attention1"].append(internals.attention1[0, agent].mean(0).cpu().numpy())
            columns["attention2"].append(internals.attention2[0, agent].mean(0).cpu().numpy())
            columns["neighbors"].append(neighbors[0, agent].cpu().numpy())
            columns["reset_gate"].append(internals.reset[0, agent].mean().cpu().numpy())
            columns["reset_gate_all"].append(internals.reset.mean().cpu().numpy())
            columns["outputs"].append(internals.out[0].cpu().numpy())
            columns["actions"].append(actions)
    return EpisodeRecord(**{name: np.stack(values) if values else None for name, values in columns.items()})
