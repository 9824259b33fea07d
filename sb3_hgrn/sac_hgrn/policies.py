"""SAC-HGRN policy: an HGRN actor (logits) and HGRN critics (Q for every action), each with its own state."""

from __future__ import annotations

from typing import Any

import torch as th
from gymnasium import spaces
from stable_baselines3.common.type_aliases import Schedule
from torch import nn

from sb3_hgrn.common.hgrn import HGRN, GraphBatch
from sb3_hgrn.common.policies import GraphObs, GraphPolicy
from sb3_hgrn.common.soft_math import BEHAVIOUR_POLICIES, sample_actions


class SACHGRNPolicy(GraphPolicy):
    """Discrete soft actor-critic on graphs: actor and ``n_critics`` critics with separate parameters.

    The carried state is ``[actor state, critic 1 state, ...]`` (see
    :meth:`~sb3_hgrn.common.policies.GraphPolicy.split_state`): every network's memory advances
    while collecting, so each transition stores the states the networks had (the actor's only where
    it trains); in deployment (:meth:`act`) only the network that chooses runs.

    The actor's policy is ``softmax(f(o))`` of its network's outputs ``f`` (its logits, as in the
    paper), or ``softmax(f(o) / alpha)`` with ``tempered_actor``. Both can express the same policies;
    tempered outputs live in the critic's units (``f = Q`` is the Boltzmann policy every actor loss
    moves toward), so the actor needs the same output changes as its critic to follow it, not
    ``1 / alpha`` times larger ones, and a change of alpha changes the actor's entropy at once
    (docs/results.md has what it did).

    The policy that collects, and that :meth:`act` (``predict``, every evaluation) deploys, is the
    actor's, or with ``behaviour_policy="critic"`` the first critic's Boltzmann policy
    ``softmax(Q / alpha)``: a model deploys the policy its training returns describe. With
    ``average_tau`` it deploys the Polyak average of that network (``actor_average`` or
    ``critic_average``, see :class:`~sb3_hgrn.common.policies.GraphPolicy`); the online networks
    collect and learn.

    :param n_critics: number of critics (2 = clipped double Q).
    :param tempered_actor: divide the actor's outputs by alpha (only for stochastic policies: a
        greedy actor's argmax does not depend on alpha).
    :param behaviour_policy: ``"actor"`` or ``"critic"``: the network whose policy collects and is
        deployed (set by :class:`~sb3_hgrn.sac_hgrn.SACHGRN` from its argument of that name).
    :param actor_kwargs: network options of the actor only (e.g. ``dict(communication="none")``).
    :param critic_kwargs: network options of the critics only.
    Other parameters: see :class:`~sb3_hgrn.common.policies.GraphPolicy`.
    """

    network_arguments = ("actor_kwargs", "critic_kwargs")

    def __init__(
        self,
        observation_space: spaces.Dict,
        action_space: spaces.Discrete,
        lr_schedule: Schedule,
        n_critics: int = 1,
        actor_kwargs: dict[str, Any] | None = None,
        critic_kwargs: dict[str, Any] | None = None,
        tempered_actor: bool = False,
        behaviour_policy: str = "actor",
        **kwargs: Any,
    ):
        super().__init__(observation_space, action_space, lr_schedule, **kwargs)
        if n_critics < 1:
            raise ValueError(f"n_critics must be >= 1, got {n_critics}.")
        if behaviour_policy not in BEHAVIOUR_POLICIES:
            raise ValueError(
                f"behaviour_policy must be one of {BEHAVIOUR_POLICIES}, got {behaviour_policy!r}."
            )
        self.n_critics = n_critics
        self.tempered_actor = tempered_actor
        self.behaviour_policy = behaviour_policy
        self.actor_kwargs = dict(actor_kwargs or {})
        self.critic_kwargs = dict(critic_kwargs or {})
        self.actor = self.make_network(**self.actor_kwargs)
        self.critics = nn.ModuleList(self.make_network(**self.critic_kwargs) for _ in range(n_critics))
        self.keep_average()
        self.critic_targets = nn.ModuleList(self.make_network(**self.critic_kwargs) for _ in range(n_critics))
        self.critic_targets.load_state_dict(self.critics.state_dict())
        self.critic_targets.requires_grad_(False)
        self.critic_targets.train(False)
        self.actor_optimizer = self.optimizer_class(
            self.actor.parameters(), lr=lr_schedule(1), **self.optimizer_kwargs
        )
        self.critic_optimizer = self.optimizer_class(
            self.critics.parameters(), lr=lr_schedule(1), **self.optimizer_kwargs
        )

    @property
    def acting_network_name(self) -> str:  # type: ignore[override]
        return self.behaviour_policy

    @property
    def acting_network_label(self) -> str:  # type: ignore[override]
        return "first critic (its Boltzmann policy)" if self.behaviour_policy == "critic" else "actor"

    @property
    def deployed_label(self) -> str:
        if self.acts_with_critic:
            return "online first critic (its Boltzmann policy)"
        return super().deployed_label

    @property
    def online_network(self) -> HGRN:
        """The network whose policy collects: the actor, or with ``behaviour_policy="critic"`` the
        first critic."""
        return self.critics[0] if self.behaviour_policy == "critic" else self.actor

    @property
    def recurrent_networks(self) -> list[HGRN]:
        return [self.actor, *self.critics]

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.update(
            n_critics=self.n_critics,
            actor_kwargs=self.actor_kwargs,
            critic_kwargs=self.critic_kwargs,
            tempered_actor=self.tempered_actor,
            behaviour_policy=self.behaviour_policy,
        )
        return data

    def actor_logits(
        self,
        observations: th.Tensor,
        graph: GraphBatch,
        state: th.Tensor,
        groups: th.Tensor | None,
        actor: nn.Module | None = None,
    ) -> tuple[th.Tensor, th.Tensor]:
        """The actor's logits ``(n_graphs, n_agents, n_actions)`` (its outputs over alpha with
        ``tempered_actor``; alpha detached) and its new state, from observations
        ``(n_graphs, n_agents, *obs_shape)``, the graphs, its state and the agents' group ids (or
        ``None``); ``actor`` is the online actor unless another (its average) is given."""
        outputs, new_state = (self.actor if actor is None else actor)(observations, graph, state)
        return self.logits(outputs, groups), new_state

    def logits(self, outputs: th.Tensor, groups: th.Tensor | None) -> th.Tensor:
        """The policy's logits from actor outputs ``(n_graphs, n_agents, n_actions)``: the outputs, or
        with ``tempered_actor`` the outputs over the agents' alpha (detached)."""
        if self.tempered_actor and self.stochastic:
            return outputs / self.temperature.per_agent(groups)
        return outputs

    acts_with_critic: bool = False
    """``act`` (so ``predict`` and evaluation) draws from the online first critic's Boltzmann policy
    whatever the model deploys; a setting of the loaded object, not saved with the model
    (``sb3-hgrn evaluate --critic``)."""

    def act(
        self, obs: GraphObs, hidden: th.Tensor, deterministic: bool = False
    ) -> tuple[th.Tensor, th.Tensor]:
        """Actions of the deployed policy (``predict`` and every evaluation): only the network that
        chooses runs (the deployed one, or the online first critic with :attr:`acts_with_critic`); the
        other networks' parts of the state, which only training reads, are returned as given."""
        if self.acts_with_critic:
            return self._act(obs, hidden, deterministic, first_critic=self.critics[0], others=False)
        if self.behaviour_policy == "critic":
            return self._act(obs, hidden, deterministic, first_critic=self.deployed_network, others=False)
        return self._act(obs, hidden, deterministic, actor=self.deployed_network, others=False)

    def act_with(
        self, network: nn.Module, obs: GraphObs, hidden: th.Tensor, deterministic: bool = False
    ) -> tuple[th.Tensor, th.Tensor]:
        """Actions drawn from the policy of ``network`` (the online actor or its average, or with
        ``behaviour_policy="critic"`` the first critic or its average: its Boltzmann policy), every
        network's memory advancing, as collection stores it."""
        if self.behaviour_policy == "critic":
            return self._act(obs, hidden, deterministic, first_critic=network)
        return self._act(obs, hidden, deterministic, actor=network)

    def critic_act(
        self, obs: GraphObs, hidden: th.Tensor, deterministic: bool = False, runs_actor: bool = True
    ) -> tuple[th.Tensor, th.Tensor]:
        """Actions drawn from the online first critic's Boltzmann policy ``softmax(Q / alpha)``
        (greedy: its argmax), every network's memory advancing as in :meth:`act_with`, except the
        actor's without ``runs_actor`` (the actor is then not run and its state is returned as given:
        collection with an actor that never trains)."""
        return self._act(obs, hidden, deterministic, first_critic=self.critics[0], runs_actor=runs_actor)

    def _act(
        self,
        obs: GraphObs,
        hidden: th.Tensor,
        deterministic: bool,
        actor: nn.Module | None = None,
        first_critic: nn.Module | None = None,
        runs_actor: bool = True,
        others: bool = True,
    ) -> tuple[th.Tensor, th.Tensor]:
        """Actions from the policy of ``actor`` (the online one if ``None``), or with
        ``first_critic`` from that network's Boltzmann policy, in the first critic's place. The
        network that chooses always runs; with ``others`` the other recurrent networks run too, so
        that their memories advance (the actor only with ``runs_actor``); a network that does not
        run returns its part of the state as given."""
        observations, neighbors, groups = self.to_graphs(obs)
        n_graphs, n_agents = observations.shape[:2]
        states = self.split_state(hidden.reshape(n_graphs, n_agents, -1))
        graph = self.graph_batch(neighbors, groups)  # shared by the actor and every critic
        actor_state = states[0]
        if first_critic is None or (others and runs_actor):
            logits, actor_state = self.actor_logits(observations, graph, states[0], groups, actor)
        new_states = [actor_state]
        for index, (critic, state) in enumerate(zip(self.critics, states[1:], strict=True)):
            acting = index == 0 and first_critic is not None
            if acting or (others and critic.state_dim):
                q_values, new_state = (first_critic if acting else critic)(observations, graph, state)
                if acting:
                    logits = q_values / self.temperature.per_agent(groups)
                state = new_state if critic.state_dim else state
            new_states.append(state)
        if deterministic or not self.stochastic:
            actions = logits.argmax(dim=-1)
        else:
            actions = sample_actions(logits)
        return actions.reshape(-1), th.cat(new_states, dim=-1).reshape(n_graphs * n_agents, -1)

    def set_training_mode(self, mode: bool) -> None:
        self.actor.train(mode)
        self.critics.train(mode)
        self.training = mode
