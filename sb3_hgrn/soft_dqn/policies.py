"""Policies of :class:`~sb3_hgrn.SoftDQN`: SB3's DQN Q-network acting with ``softmax(Q / alpha)``."""

from __future__ import annotations

import torch as th
from stable_baselines3.common.type_aliases import PyTorchObs

from sb3_hgrn.common.single_agent import CnnPolicyMixin, MultiInputPolicyMixin, SoftDiscretePolicy


class SoftDQNPolicy(SoftDiscretePolicy):
    """SB3's ``DQNPolicy`` (``q_net``, ``q_net_target``, ``optimizer``) acting with the Boltzmann
    policy of its Q-values: ``predict`` samples ``softmax(Q / alpha)``, or takes the greedy action
    when deterministic. Options as SB3's ``DQNPolicy``, plus ``alpha_log_space``."""

    def action_logits(self, obs: PyTorchObs) -> th.Tensor:
        """``Q(obs, .) / alpha`` ``(batch, n_actions)``."""
        return self.q_net(obs) / self.temperature.per_agent(None)


class CnnPolicy(CnnPolicyMixin, SoftDQNPolicy):
    """:class:`SoftDQNPolicy` with SB3's ``NatureCNN`` for image observations."""


class MultiInputPolicy(MultiInputPolicyMixin, SoftDQNPolicy):
    """:class:`SoftDQNPolicy` with SB3's ``CombinedExtractor`` for dict observations."""


MlpPolicy = SoftDQNPolicy
