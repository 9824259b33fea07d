"""What the single-agent soft algorithms (:class:`~sb3_hgrn.SoftDQN`, :class:`~sb3_hgrn.DiscreteSAC`)
share: their env check, their policy base and the plain SB3 replay samples as the tensors of the
shared losses (:mod:`sb3_hgrn.common.soft_math`)."""

from __future__ import annotations

from typing import Any, ClassVar, NamedTuple

import torch as th
from gymnasium import spaces
from stable_baselines3.common.base_class import maybe_make_env
from stable_baselines3.common.torch_layers import (
    BaseFeaturesExtractor,
    CombinedExtractor,
    FlattenExtractor,
    NatureCNN,
)
from stable_baselines3.common.type_aliases import GymEnv, PyTorchObs, ReplayBufferSamples, Schedule
from stable_baselines3.dqn.policies import DQNPolicy

from sb3_hgrn.common.optimizers import fused_by_default
from sb3_hgrn.common.soft_math import sample_actions
from sb3_hgrn.common.temperature import EntropyTemperature
from sb3_hgrn.envs.registration import ensure_registered

TEMPERATURE_SAVE_PARAMS = ["temperature.optimizer"]
"""The state dict a single-agent soft algorithm saves besides its policy's: the temperature optimiser's."""


def check_discrete_env(env: GymEnv | str | None, algorithm: str, verbose: int = 0) -> GymEnv | None:
    """``env`` (made from its id when it is a string, as SB3 does, after registering the id's
    namespace where a plugin package declares it: :func:`~sb3_hgrn.envs.registration.ensure_registered`)
    after checking that its action space is ``Discrete``; raises a ``TypeError`` naming the space
    otherwise.

    :param algorithm: the algorithm's name, for the message.
    """
    if env is None:
        return None
    env = maybe_make_env(ensure_registered(env) if isinstance(env, str) else env, verbose)
    space = env.action_space
    if not isinstance(space, spaces.Discrete):
        raise TypeError(
            f"{algorithm} needs an env with a Discrete action space, got {type(space).__name__} {space}. "
            "For continuous (Box) actions use SB3's SAC or TD3; for MultiDiscrete or MultiBinary actions, "
            "PPO or A2C."
        )
    return env


class Transitions(NamedTuple):
    """The replay samples as the shared losses take them: ``rewards``, ``terminated`` and
    ``discounts`` (``gamma ** n`` of n-step returns, or ``gamma``) ``(batch,)``, ``actions``
    ``(batch, 1)`` int64 and the ``mask`` of counted entries ``(batch,)`` (all ones)."""

    rewards: th.Tensor
    terminated: th.Tensor
    discounts: th.Tensor | float
    actions: th.Tensor
    mask: th.Tensor


def transitions(data: ReplayBufferSamples, gamma: float) -> Transitions:
    """:class:`Transitions` of SB3's replay samples (``(batch, 1)`` rewards, dones and discounts)."""
    rewards = data.rewards.reshape(-1)
    discounts = gamma if data.discounts is None else data.discounts.reshape(-1)
    return Transitions(
        rewards, data.dones.reshape(-1), discounts, data.actions.long().reshape(-1, 1), th.ones_like(rewards)
    )


class SoftDiscretePolicy(DQNPolicy):
    """Base of the single-agent soft policies: SB3's ``DQNPolicy`` (its Q-network builder,
    features extractors and options) with a learned temperature ``temperature`` and a stochastic
    ``predict`` that samples ``softmax(action_logits)`` (the greedy action when deterministic).

    Subclasses define :meth:`action_logits`; their image and dict-observation variants only change
    ``default_extractor``.

    :param alpha_log_space: learn ``log(alpha)`` instead of alpha.
    :param features_extractor_class: ``None`` for ``default_extractor``.
    :param optimizer_kwargs: as SB3's; for ``Adam`` and ``AdamW`` they default to ``fused=True`` (one
        kernel per step for all parameters) unless they name ``fused`` or ``foreach``: on these small
        networks the per-parameter steps of SB3's default are a large share of a gradient step.
    """

    default_extractor: ClassVar[type[BaseFeaturesExtractor]] = FlattenExtractor
    n_groups = 1

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Discrete,
        lr_schedule: Schedule,
        features_extractor_class: type[BaseFeaturesExtractor] | None = None,
        alpha_log_space: bool = False,
        optimizer_class: type[th.optim.Optimizer] = th.optim.Adam,
        optimizer_kwargs: dict[str, Any] | None = None,
        **kwargs: Any,
    ):
        super().__init__(
            observation_space,
            action_space,
            lr_schedule,
            features_extractor_class=features_extractor_class or self.default_extractor,
            optimizer_class=optimizer_class,
            optimizer_kwargs=fused_by_default(optimizer_class, optimizer_kwargs),
            **kwargs,
        )
        self.alpha_log_space = alpha_log_space
        self.temperature = EntropyTemperature(log_space=alpha_log_space)

    @property
    def action_counts(self) -> list[int]:
        """The action count, as the graph policies give one per agent group."""
        return [int(self.action_space.n)]

    def action_logits(self, obs: PyTorchObs) -> th.Tensor:
        """Logits ``(batch, n_actions)`` of the acting policy."""
        raise NotImplementedError

    def _predict(self, obs: PyTorchObs, deterministic: bool = True) -> th.Tensor:
        logits = self.action_logits(obs)
        if deterministic:
            return logits.argmax(dim=-1)
        return sample_actions(logits)

    def _get_constructor_parameters(self) -> dict[str, Any]:
        return {**super()._get_constructor_parameters(), "alpha_log_space": self.alpha_log_space}


class CnnPolicyMixin:
    """Makes a :class:`SoftDiscretePolicy` default to SB3's ``NatureCNN`` for image observations."""

    default_extractor = NatureCNN


class MultiInputPolicyMixin:
    """Makes a :class:`SoftDiscretePolicy` default to SB3's ``CombinedExtractor`` for dict observations."""

    default_extractor = CombinedExtractor
