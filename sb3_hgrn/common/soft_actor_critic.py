"""The discrete soft actor-critic gradient step shared by :class:`~sb3_hgrn.SACHGRN` and
:class:`~sb3_hgrn.DiscreteSAC`: each gathers its batch its own way (graphs and recurrent state, or
SB3's plain replay samples) and hands the Q-values, targets and actor to :meth:`SoftActorCritic._sac_step`."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch as th
from stable_baselines3.common.utils import polyak_update

from sb3_hgrn.common.soft_math import (
    BEHAVIOUR_POLICIES,
    CRITIC_TARGETS,
    actor_loss,
    critic_minimum,
    gradient_step,
    masked_mean,
    q_regression_loss,
    sac_next_value,
    soft_q_next_value,
    steered_entropy,
)
from sb3_hgrn.common.temperature import TemperatureLearner, categorical_entropy
from sb3_hgrn.validation import is_integer


def with_behaviour_policy(
    policy_kwargs: dict[str, Any] | None, behaviour_policy: str, algorithm: str
) -> dict[str, Any]:
    """``policy_kwargs`` with the algorithm's ``behaviour_policy`` (which the policy acts with), after
    a ``ValueError`` for one not in :data:`~sb3_hgrn.common.soft_math.BEHAVIOUR_POLICIES` or for
    ``policy_kwargs`` naming another; ``algorithm`` names the class in the message."""
    if behaviour_policy not in BEHAVIOUR_POLICIES:
        raise ValueError(f"behaviour_policy must be one of {BEHAVIOUR_POLICIES}, got {behaviour_policy!r}.")
    given = (policy_kwargs or {}).get("behaviour_policy", behaviour_policy)
    if given != behaviour_policy:
        raise ValueError(
            f"policy_kwargs.behaviour_policy={given!r} disagrees with behaviour_policy={behaviour_policy!r}; "
            f"give {algorithm}'s behaviour_policy argument only."
        )
    return {**(policy_kwargs or {}), "behaviour_policy": behaviour_policy}


AUTO_ACTOR_STEPS = "auto"
"""``actor_steps="auto"``: 1 where something reads the actor, else 0 (:func:`resolve_actor_steps`)."""


def actor_readers(behaviour_policy: str, critic_target: str, alpha_entropy: str) -> list[str]:
    """The options (``"name='actor'"``) that read the actor: it collects (``behaviour_policy``), gives
    the targets (``critic_target``) or the entropy alpha steers by (``alpha_entropy``)."""
    readers = {
        "behaviour_policy": behaviour_policy,
        "critic_target": critic_target,
        "alpha_entropy": alpha_entropy,
    }
    return [f"{name}={value!r}" for name, value in readers.items() if value == "actor"]


def resolve_actor_steps(
    actor_steps: int | str, behaviour_policy: str, critic_target: str, alpha_entropy: str
) -> int:
    """``actor_steps`` as the number of actor steps per critic step: ``"auto"`` is 1 where an option
    reads the actor (:func:`actor_readers`) and 0 where none does (training an actor nothing reads
    changes nothing the model does); an integer is checked by :func:`check_actor_steps`."""
    if actor_steps == AUTO_ACTOR_STEPS:
        return 1 if actor_readers(behaviour_policy, critic_target, alpha_entropy) else 0
    check_actor_steps(actor_steps, behaviour_policy, critic_target, alpha_entropy)
    return int(actor_steps)


def check_actor_steps(
    actor_steps: int, behaviour_policy: str, critic_target: str, alpha_entropy: str
) -> None:
    """Raise a ``ValueError`` unless ``actor_steps`` is an integer >= 0, and unless, with 0 (the actor
    never trained), nothing reads the actor (:func:`actor_readers`)."""
    if not is_integer(actor_steps) or actor_steps < 0:
        raise ValueError(f"actor_steps must be an integer >= 0 or {AUTO_ACTOR_STEPS!r}, got {actor_steps!r}.")
    reading = actor_readers(behaviour_policy, critic_target, alpha_entropy)
    if actor_steps == 0 and reading:
        raise ValueError(
            f"actor_steps=0 leaves the actor untrained, but {', '.join(reading)} reads it; use "
            "behaviour_policy='critic', critic_target='boltzmann' and alpha_entropy='boltzmann' with it."
        )


def check_critic_target(critic_target: str) -> None:
    """Raise a ``ValueError`` unless ``critic_target`` is one of
    :data:`~sb3_hgrn.common.soft_math.CRITIC_TARGETS`."""
    if critic_target not in CRITIC_TARGETS:
        raise ValueError(f"critic_target must be one of {CRITIC_TARGETS}, got {critic_target!r}.")


@dataclass
class SACFigures:
    """What one training round of gradient steps logs, one entry per step."""

    critic_losses: list[float] = field(default_factory=list)
    actor_losses: list[float] = field(default_factory=list)
    actor_entropies: list[float] = field(default_factory=list)
    entropies: list[th.Tensor] = field(default_factory=list)
    alpha_gradients: list[th.Tensor] = field(default_factory=list)


class SoftActorCritic(TemperatureLearner):
    """Mixin of the discrete-SAC algorithms: targets, losses, one gradient step and its logs.

    The algorithm provides ``policy`` (``actor``, ``critics``, ``critic_targets``,
    ``actor_optimizer``, ``critic_optimizer`` and what :class:`TemperatureLearner` needs), the
    options ``behaviour_policy``, ``actor_loss``, ``alpha_entropy``,
    ``critic_target``, ``actor_steps``, ``stochastic``, ``max_grad_norm``, ``tau`` and
    ``target_update_interval`` (gradient steps), and SB3's ``_n_updates``.
    """

    policy: Any
    behaviour_policy: str
    actor_loss: str
    alpha_entropy: str
    critic_target: str
    actor_steps: int
    stochastic: bool
    max_grad_norm: float
    tau: float
    target_update_interval: int
    _n_updates: int

    def _resolve_loaded_actor_steps(self) -> None:
        """:func:`resolve_actor_steps` of a loaded model's options (``load``'s arguments may give
        ``actor_steps="auto"``, or set an option that reads an actor trained with ``actor_steps=0``,
        that is not at all: a ``ValueError``)."""
        self.actor_steps = resolve_actor_steps(
            self.actor_steps, self.behaviour_policy, self.critic_target, self.alpha_entropy
        )

    def _next_value(
        self, next_q: th.Tensor, next_logits: Callable[[], th.Tensor], alpha: th.Tensor
    ) -> th.Tensor:
        """Value ``(...)`` of the next observations from the target critics' minimum ``next_q``
        ``(..., n_actions)``. With ``critic_target="actor"`` it is the exact soft expectation over
        the actor's policy, whose logits ``next_logits()`` computes (or the Q-value of its greedy
        action for ``stochastic=False``; :func:`~sb3_hgrn.common.soft_math.sac_next_value`). With
        ``"boltzmann"`` it is that over ``softmax(next_q / alpha)``, the soft value (or the greedy
        maximum; :func:`~sb3_hgrn.common.soft_math.soft_q_next_value`), and the actor is not run."""
        if self.critic_target == "boltzmann":
            return soft_q_next_value(next_q, alpha, self.stochastic)
        return sac_next_value(next_q, next_logits(), alpha, self.stochastic)

    def _policy_loss(
        self, logits: th.Tensor, q_values: th.Tensor, alpha: th.Tensor, mask: th.Tensor
    ) -> th.Tensor:
        """Actor loss from its logits and the (detached) critic Q-values ``(..., n_actions)``, averaged
        over the entries of ``mask`` ``(...)`` (1 or 0; :func:`~sb3_hgrn.common.soft_math.actor_loss`)."""
        return actor_loss(self.actor_loss, logits, q_values, alpha, mask, self.stochastic)

    def _after_actor_steps(self) -> None:
        """Called once the actor has taken its steps, before alpha's (nothing by default)."""

    def _sac_step(
        self,
        q_values: list[th.Tensor],
        actions: th.Tensor,
        target_q: th.Tensor,
        actor_logits: Callable[[], th.Tensor],
        alpha: th.Tensor,
        groups: th.Tensor | None,
        mask: th.Tensor,
        figures: SACFigures,
    ) -> None:
        """One gradient step of the critics, ``actor_steps`` of the actor (none with 0: the actor is
        then never run), one of alpha and, every ``target_update_interval`` steps, the critic
        targets; the figures are added to ``figures``.

        :param q_values: every critic's Q-values ``(..., n_actions)`` (with their graph).
        :param actions: the taken actions ``(..., 1)`` (int64).
        :param target_q: the regression target ``(...)``.
        :param actor_logits: computes the actor's logits ``(..., n_actions)`` (with their graph).
        :param alpha: ``(1,)`` or per entry ``(..., 1)``, detached.
        :param groups: agent groups ``(...)`` or ``None`` (one group).
        :param mask: 1 for the entries that count, 0 for the others ``(...)``.
        """
        policy = self.policy
        critic_loss = sum(q_regression_loss(q, actions, target_q, mask) for q in q_values)
        gradient_step(policy.critic_optimizer, critic_loss, policy.critics, self.max_grad_norm)

        min_q = critic_minimum([q.detach() for q in q_values])
        for _ in range(self.actor_steps):
            logits = actor_logits()
            loss = self._policy_loss(logits, min_q, alpha, mask)
            gradient_step(policy.actor_optimizer, loss, policy.actor, self.max_grad_norm)
        self._after_actor_steps()

        actor_entropy = categorical_entropy(logits.detach()) if self.actor_steps else None
        steered = steered_entropy(self.alpha_entropy, actor_entropy, min_q, alpha)
        entropy, alpha_gradient = self._update_temperature(steered, groups, mask)
        if self.actor_steps:
            figures.actor_entropies.append(masked_mean(actor_entropy, mask).item())
            figures.actor_losses.append(loss.item())
        if alpha_gradient is not None:
            figures.alpha_gradients.append(alpha_gradient)
        figures.critic_losses.append(critic_loss.item())
        figures.entropies.append(entropy)
        self._n_updates += 1
        if self._n_updates % self.target_update_interval == 0:
            polyak_update(policy.critics.parameters(), policy.critic_targets.parameters(), self.tau)

    def _record_sac(self, figures: SACFigures) -> None:
        """Log the figures of a training round: losses, the actor's entropy and the temperature's."""
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        self.logger.record("train/critic_loss", float(np.mean(figures.critic_losses)))
        if figures.actor_losses:  # none with actor_steps=0
            self.logger.record("train/actor_loss", float(np.mean(figures.actor_losses)))
            self.logger.record("train/actor_entropy", float(np.mean(figures.actor_entropies)))
        self._record_temperature(figures.entropies, figures.alpha_gradients)
