"""Soft-HGRN policy: an HGRN Q-network, its target copy, and the Boltzmann policy softmax(Q / alpha)."""

from __future__ import annotations

from typing import Any

import torch as th
from gymnasium import spaces
from stable_baselines3.common.type_aliases import Schedule
from torch import nn

from sb3_hgrn.common.hgrn import HGRN
from sb3_hgrn.common.policies import GraphObs, GraphPolicy
from sb3_hgrn.common.soft_math import sample_actions


class SoftHGRNPolicy(GraphPolicy):
    """Q-network and target Q-network (HGRN) with a learned temperature.

    Acts by sampling ``softmax(Q / alpha)``, or greedily with ``deterministic=True`` or
    ``stochastic=False``; with ``average_tau`` the deployed Q-network is the Polyak average
    ``q_net_average``. Parameters: see :class:`~sb3_hgrn.common.policies.GraphPolicy`.
    """

    acting_network_name = "q_net"
    acting_network_label = "Q-network"

    def __init__(
        self,
        observation_space: spaces.Dict,
        action_space: spaces.Discrete,
        lr_schedule: Schedule,
        **kwargs: Any,
    ):
        super().__init__(observation_space, action_space, lr_schedule, **kwargs)
        self.q_net = self.make_network()
        self.q_net_target = self.make_network()
        self.q_net_target.load_state_dict(self.q_net.state_dict())
        self.q_net_target.requires_grad_(False)
        self.q_net_target.train(False)
        self.keep_average()
        self.optimizer = self.optimizer_class(
            self.q_net.parameters(), lr=lr_schedule(1), **self.optimizer_kwargs
        )

    @property
    def recurrent_networks(self) -> list[HGRN]:
        return [self.q_net]

    def act_with(
        self, q_net: nn.Module, obs: GraphObs, hidden: th.Tensor, deterministic: bool = False
    ) -> tuple[th.Tensor, th.Tensor]:
        """Actions ``(n_slots,)`` and new state ``(n_slots, state_dim)`` of ``q_net``: sampled from
        ``softmax(Q / alpha)``, or its argmax (see :meth:`act`)."""
        observations, neighbors, groups = self.to_graphs(obs)
        n_graphs, n_agents = observations.shape[:2]
        graph = self.graph_batch(neighbors, groups)
        q_values, new_hidden = q_net(observations, graph, hidden.reshape(n_graphs, n_agents, -1))
        if deterministic or not self.stochastic:
            actions = q_values.argmax(dim=-1)
        else:
            logits = q_values / self.temperature.per_agent(groups)
            actions = sample_actions(logits)
        return actions.reshape(-1), new_hidden.reshape(n_graphs * n_agents, -1)

    def set_training_mode(self, mode: bool) -> None:
        self.q_net.train(mode)
        self.training = mode
