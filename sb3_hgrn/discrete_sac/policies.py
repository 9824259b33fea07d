"""Policies of :class:`~sb3_hgrn.DiscreteSAC`: a categorical actor and twin Q-critics, as SB3 builds DQN."""

from __future__ import annotations

from typing import Any

import torch as th
from gymnasium import spaces
from stable_baselines3.common.type_aliases import PyTorchObs, Schedule
from torch import nn

from sb3_hgrn.common.single_agent import CnnPolicyMixin, MultiInputPolicyMixin, SoftDiscretePolicy
from sb3_hgrn.common.soft_math import BEHAVIOUR_POLICIES


class DiscreteSACPolicy(SoftDiscretePolicy):
    """Actor ``actor`` (logits ``(batch, n_actions)``) and ``n_critics`` critics ``critics`` with their
    targets ``critic_targets`` (Q-values ``(batch, n_actions)``), each network built as SB3's DQN
    Q-network with its own features extractor; ``actor_optimizer`` and ``critic_optimizer``.
    ``predict`` samples the acting policy, or takes its most likely action when deterministic: the
    actor's, or with ``behaviour_policy="critic"`` the first critic's Boltzmann policy
    ``softmax(Q / alpha)``, which then also collects.

    :param n_critics: number of critics (the target takes their minimum).
    :param behaviour_policy: ``"actor"`` or ``"critic"`` (set by :class:`~sb3_hgrn.DiscreteSAC` from
        its argument of that name).
    Other options as SB3's ``DQNPolicy`` (``net_arch`` is that of every network), plus ``alpha_log_space``.
    """

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Discrete,
        lr_schedule: Schedule,
        n_critics: int = 2,
        behaviour_policy: str = "actor",
        **kwargs: Any,
    ):
        if not isinstance(n_critics, int) or n_critics < 1:
            raise ValueError(f"n_critics must be a positive integer, got {n_critics!r}.")
        if behaviour_policy not in BEHAVIOUR_POLICIES:
            raise ValueError(
                f"behaviour_policy must be one of {BEHAVIOUR_POLICIES}, got {behaviour_policy!r}."
            )
        self.n_critics = n_critics
        self.behaviour_policy = behaviour_policy
        super().__init__(observation_space, action_space, lr_schedule, **kwargs)

    def _build(self, lr_schedule: Schedule) -> None:
        """Build the actor, the critics, their targets (in evaluation mode) and both optimisers."""
        self.actor = self.make_q_net()
        self.critics = nn.ModuleList(self.make_q_net() for _ in range(self.n_critics))
        self.critic_targets = nn.ModuleList(self.make_q_net() for _ in range(self.n_critics))
        self.critic_targets.load_state_dict(self.critics.state_dict())
        self.critic_targets.train(False)
        self.actor_optimizer = self.optimizer_class(
            self.actor.parameters(), lr=lr_schedule(1), **self.optimizer_kwargs
        )
        self.critic_optimizer = self.optimizer_class(
            self.critics.parameters(), lr=lr_schedule(1), **self.optimizer_kwargs
        )

    def action_logits(self, obs: PyTorchObs) -> th.Tensor:
        """The acting policy's logits ``(batch, n_actions)``: the actor's, or with
        ``behaviour_policy="critic"`` the first critic's Q-values over alpha."""
        if self.behaviour_policy == "critic":
            return self.critics[0](obs) / self.temperature.per_agent(None)
        return self.actor(obs)

    def set_training_mode(self, mode: bool) -> None:
        self.actor.set_training_mode(mode)
        self.critics.train(mode)
        self.training = mode

    def _get_constructor_parameters(self) -> dict[str, Any]:
        return {
            **super()._get_constructor_parameters(),
            "n_critics": self.n_critics,
            "behaviour_policy": self.behaviour_policy,
        }


class CnnPolicy(CnnPolicyMixin, DiscreteSACPolicy):
    """:class:`DiscreteSACPolicy` with SB3's ``NatureCNN`` for image observations."""


class MultiInputPolicy(MultiInputPolicyMixin, DiscreteSACPolicy):
    """:class:`DiscreteSACPolicy` with SB3's ``CombinedExtractor`` for dict observations."""


MlpPolicy = DiscreteSACPolicy
