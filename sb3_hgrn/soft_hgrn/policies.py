"""Soft-HGRN policy: an HGRN Q-network, its target copy, and the Boltzmann policy softmax(Q / alpha)."""

from __future__ import annotations

from typing import Any

import torch as th
from gymnasium import spaces
from stable_baselines3.common.type_aliases import Schedule
from torch import nn

from sb3_hgrn.common.averaging import polyak_average
from sb3_hgrn.common.hgrn import HGRN
from sb3_hgrn.common.policies import GraphObs, GraphPolicy


class SoftHGRNPolicy(GraphPolicy):
    """Q-network and target Q-network (HGRN) with a learned temperature.

    Acts by sampling ``softmax(Q / alpha)``, or greedily with ``deterministic=True`` or
    ``stochastic=False``. Parameters: see :class:`~sb3_hgrn.common.policies.GraphPolicy`, and

    :param average_tau: keep a Polyak average of the Q-network's weights, updated after every
        gradient step (:meth:`update_average`; the plain mean of the first ``1 / average_tau``
        iterates, then ``average <- (1 - tau) average + tau online``), and let :meth:`act`, hence
        ``predict`` and every evaluation, act with it. Collecting experience and the TD targets
        keep using the online and the target network. ``None``: act with the online network.
    """

    def __init__(
        self,
        observation_space: spaces.Dict,
        action_space: spaces.Discrete,
        lr_schedule: Schedule,
        average_tau: float | None = None,
        **kwargs: Any,
    ):
        super().__init__(observation_space, action_space, lr_schedule, **kwargs)
        if average_tau is not None and not 0 < average_tau <= 1:
            raise ValueError(f"average_tau must be in (0, 1] or None, got {average_tau}.")
        self.average_tau = average_tau
        self.q_net = self.make_network()
        self.q_net_target = self.make_network()
        self.q_net_target.load_state_dict(self.q_net.state_dict())
        self.q_net_target.requires_grad_(False)
        self.q_net_target.train(False)
        self.q_net_average = None if average_tau is None else polyak_average(self.q_net, average_tau)
        self.optimizer = self.optimizer_class(
            self.q_net.parameters(), lr=lr_schedule(1), **self.optimizer_kwargs
        )

    @property
    def recurrent_networks(self) -> list[HGRN]:
        return [self.q_net]

    def _get_constructor_parameters(self) -> dict[str, Any]:
        return {**super()._get_constructor_parameters(), "average_tau": self.average_tau}

    def update_average(self) -> None:
        """Add the online Q-network's weights to the average (no-op without ``average_tau``)."""
        if self.q_net_average is not None:
            self.q_net_average.update_parameters(self.q_net)

    def drop_average(self) -> None:
        """Forget the averaged Q-network: act with the online one from now on."""
        self.q_net_average = None
        self.average_tau = None

    def act(
        self, obs: GraphObs, hidden: th.Tensor, deterministic: bool = False
    ) -> tuple[th.Tensor, th.Tensor]:
        """Actions of the deployed Q-network: the average with ``average_tau``, else the online one."""
        q_net = self.q_net if self.q_net_average is None else self.q_net_average
        return self.act_with(q_net, obs, hidden, deterministic)

    def act_with(
        self, q_net: nn.Module, obs: GraphObs, hidden: th.Tensor, deterministic: bool = False
    ) -> tuple[th.Tensor, th.Tensor]:
        """Actions ``(n_slots,)`` and new state ``(n_slots, state_dim)`` of ``q_net`` (see :meth:`act`)."""
        observations, neighbors, groups = self.to_graphs(obs)
        n_graphs, n_agents = observations.shape[:2]
        graph = self.graph_batch(neighbors, groups)
        q_values, new_hidden = q_net(observations, graph, hidden.reshape(n_graphs, n_agents, -1))
        if deterministic or not self.stochastic:
            actions = q_values.argmax(dim=-1)
        else:
            logits = q_values / self.temperature.per_agent(groups)
            actions = th.distributions.Categorical(logits=logits).sample()
        return actions.reshape(-1), new_hidden.reshape(n_graphs * n_agents, -1)

    def set_training_mode(self, mode: bool) -> None:
        self.q_net.train(mode)
        self.training = mode
