"""Learned temperature that keeps a policy's action entropy at a target, shared by the soft algorithms.

The target is ``target_entropy_ratio * log(n_actions)``. After each critic step the mean policy
entropy ``H`` of the batch is measured and the learned parameter (alpha, or ``log(alpha)`` with
``log_space``) takes one optimiser step on ``loss = param * (H - H_target)``: its gradient
``H - H_target`` lowers alpha while the policy is more random than the target and raises it while
the policy is too greedy. One update changes alpha by at most ``max_step_ratio`` of its value (the
algorithms' ``alpha_max_step``: 1 % as in the paper, 5 % by default for SoftHGRN and SACHGRN), whatever the
optimiser: the bound applies to the step the optimiser took, not to the gradient (Adam normalises
gradients, so a gradient bound would not bound its steps). Alpha stays above ``min_alpha``.

With ``alpha_init="auto"`` alpha starts, at the first gradient step, at ``0.1`` times the standard
deviation of the rewards stored by then (the agents' rewards of the warm-up steps), so that it starts
on the scale of the differences between the actions' values whatever the env's reward scale (0.1
when the stored rewards do not vary). A fixed start far above that scale keeps the policy close to
uniform, and its soft targets close to the values of the random policy, for the hundreds of updates
alpha takes to come down at 1 % per update (``docs/results_defaults.md``).

With several agent groups every group has its own alpha and its own target from its own action
count, and each group's alpha follows the mean entropy of that group's agents. A group absent from
a batch (no living agent of it) is left exactly as it was by that update: its alpha and its
optimiser state (Adam's moment estimates, SGD's momentum) are restored after the step, so momentum
gathered while it was present does not move it while it is absent. The optimiser's step count is
shared by all groups and does advance.
"""

from __future__ import annotations

import math
import numbers
from typing import Any

import numpy as np
import torch as th
from torch import nn

ALPHA_OPTIMIZERS = {"adam": th.optim.Adam, "sgd": th.optim.SGD}

AUTO_ALPHA = "auto"
"""``alpha_init`` value that starts alpha from the stored rewards' scale (see :func:`alpha_from_rewards`)."""

AUTO_ALPHA_REWARD_SCALE = 0.1
"""``alpha_init="auto"`` starts alpha at this multiple of the stored rewards' standard deviation."""

FALLBACK_ALPHA = 0.1
"""Alpha of ``alpha_init="auto"`` before the first gradient step, and when the rewards do not vary."""


def check_alpha_init(alpha_init: float | str) -> None:
    """Raise ``ValueError`` unless ``alpha_init`` is a number > 0 or ``"auto"``."""
    if alpha_init == AUTO_ALPHA:
        return
    if isinstance(alpha_init, bool) or not isinstance(alpha_init, numbers.Real) or not alpha_init > 0:
        raise ValueError(f'alpha_init must be a number > 0 or "auto", got {alpha_init!r}.')


def alpha_from_rewards(rewards: np.ndarray) -> float:
    """The starting alpha of ``alpha_init="auto"``: :data:`AUTO_ALPHA_REWARD_SCALE` times the standard
    deviation of ``rewards`` (the per-agent rewards stored so far, any shape), or
    :data:`FALLBACK_ALPHA` when there are none or they do not vary."""
    rewards = np.asarray(rewards, dtype=np.float64)
    if not rewards.size:
        return FALLBACK_ALPHA
    spread, level = float(rewards.std()), float(np.abs(rewards.mean()))
    varies = math.isfinite(spread) and spread > 1e-6 * level and spread > 0  # not float rounding alone
    return AUTO_ALPHA_REWARD_SCALE * spread if varies else FALLBACK_ALPHA


def check_max_step_ratio(max_step_ratio: float) -> None:
    """Raise ``ValueError`` unless ``max_step_ratio`` (``alpha_max_step``) lies in ``(0, 1)``."""
    if not 0.0 < max_step_ratio < 1.0:
        raise ValueError(f"alpha_max_step (max_step_ratio) must lie in (0, 1), got {max_step_ratio}.")


class EntropyTemperature(nn.Module):
    """The temperature alpha of every agent group as a learnable parameter ``(n_groups,)`` (raw alpha,
    or its log with ``log_space``).

    It lives in the policy, so it is saved with the policy and ``predict`` can sample from
    ``softmax(Q / alpha)``.
    """

    def __init__(self, initial_alpha: float = 0.1, log_space: bool = False, n_groups: int = 1):
        super().__init__()
        if initial_alpha <= 0:
            raise ValueError(f"initial_alpha must be > 0, got {initial_alpha}.")
        self.log_space = log_space
        self.param = nn.Parameter(th.zeros(n_groups))
        self.reset(initial_alpha)

    def reset(self, alpha: float) -> None:
        """Set every group's alpha to ``alpha``."""
        with th.no_grad():
            self.param.fill_(math.log(alpha) if self.log_space else alpha)

    @property
    def alpha(self) -> th.Tensor:
        """Alpha ``(n_groups,)`` > 0 (carries gradient to ``param``)."""
        return self.param.exp() if self.log_space else self.param

    def per_agent(self, groups: th.Tensor | None) -> th.Tensor:
        """Detached alpha of every agent: ``(batch, n_agents, 1)`` from group ids ``(batch, n_agents)``,
        or ``(1,)`` (broadcasting over everything) when there is one group."""
        alpha = self.alpha.detach()
        return alpha if groups is None else alpha[groups].unsqueeze(-1)


def target_entropy(ratio: float, n_actions: int) -> float:
    """Target entropy ``ratio * log(n_actions)`` in nats; ``ratio`` must lie in [0, 1]."""
    if not 0.0 <= ratio <= 1.0:
        raise ValueError(f"target_entropy_ratio must be within [0, 1], got {ratio}.")
    return ratio * math.log(n_actions)


def categorical_entropy(logits: th.Tensor) -> th.Tensor:
    """Entropy in nats of ``softmax(logits)`` along the last axis: ``(...)`` from ``(..., n_actions)``."""
    log_probs = th.log_softmax(logits, dim=-1)
    return -(log_probs.exp() * log_probs).sum(dim=-1)


def group_means(
    values: th.Tensor, groups: th.Tensor | None, n_groups: int, weights: th.Tensor | None = None
) -> th.Tensor:
    """Mean of ``values`` ``(batch, n_agents)`` over the agents of each group: ``(n_groups,)``
    (NaN for a group absent from the batch). With ``weights`` ``(batch, n_agents)`` (1 for the
    agents to count, 0 for the others, e.g. agents gone from their episode) only the counted agents
    take part."""
    weights = th.ones_like(values) if weights is None else weights.to(values.dtype)
    if groups is None:
        return ((values * weights).sum() / weights.sum()).reshape(1)
    flat_groups = groups.reshape(-1)
    zeros = values.new_zeros(n_groups)
    totals = zeros.index_add(0, flat_groups, (values * weights).reshape(-1))
    return totals / zeros.index_add(0, flat_groups, weights.reshape(-1))


class TemperatureController:
    """Optimises an :class:`EntropyTemperature` toward a target entropy.

    :param temperature: the policy's temperature module.
    :param target: target entropy in nats of every group ``(n_groups,)``.
    :param optimizer: ``"adam"`` or ``"sgd"``.
    :param learning_rate: learning rate of that optimiser.
    :param max_step_ratio: one update moves alpha within ``[(1 - r) alpha, (1 + r) alpha]``.
    :param min_alpha: lower bound of alpha.
    """

    def __init__(
        self,
        temperature: EntropyTemperature,
        target: float | th.Tensor,
        optimizer: str = "adam",
        learning_rate: float = 1e-3,
        max_step_ratio: float = 0.01,
        min_alpha: float = 1e-5,
    ):
        if optimizer not in ALPHA_OPTIMIZERS:
            raise ValueError(f"alpha_optimizer must be one of {sorted(ALPHA_OPTIMIZERS)}, got {optimizer!r}.")
        self.temperature = temperature
        self.target = th.as_tensor(target, dtype=th.float32).reshape(-1)
        check_max_step_ratio(max_step_ratio)
        self.max_step_ratio = max_step_ratio
        self.min_alpha = min_alpha
        self.optimizer = ALPHA_OPTIMIZERS[optimizer]([temperature.param], lr=learning_rate)

    def update(self, entropy: th.Tensor) -> th.Tensor:
        """One step toward the target given the measured mean entropy of every group ``(n_groups,)``
        (NaN for a group absent from the batch: its alpha and optimiser state stay as they are);
        returns alpha's mean gradient ``()`` on alpha's device (read it once per round: reading it
        waits for the device)."""
        temperature = self.temperature
        entropy = entropy.detach().reshape(-1)
        absent = th.isnan(entropy)
        gap = th.where(absent, th.zeros_like(entropy), entropy - self.target.to(entropy))
        before = temperature.alpha.detach().clone()
        kept_param = temperature.param.detach().clone()
        kept_state = self._per_group_state(temperature.param)
        # The loss is sum(param * (H - H_target)), so its gradient is the gap itself: no backward pass.
        temperature.param.grad = gap.to(temperature.param).expand_as(temperature.param).clone()
        self.optimizer.step()
        with th.no_grad():
            alpha = temperature.alpha.clamp(
                before * (1.0 - self.max_step_ratio), before * (1.0 + self.max_step_ratio)
            )
            alpha = alpha.clamp(min=self.min_alpha)
            stepped = alpha.log() if temperature.log_space else alpha
            temperature.param.copy_(th.where(absent, kept_param, stepped))
            state = self.optimizer.state[temperature.param]
            for name, value in kept_state.items():
                state[name].copy_(th.where(absent, value, state[name]))
        temperature.param.grad = None
        return gap.mean()

    def _per_group_state(self, param: nn.Parameter) -> dict[str, th.Tensor]:
        """Copies of the optimiser's state tensors of ``param`` that hold one entry per group
        ``(n_groups,)`` (Adam's moments, SGD's momentum buffer), by name; none before its first step."""
        return {
            name: value.detach().clone()
            for name, value in self.optimizer.state[param].items()
            if isinstance(value, th.Tensor) and value.shape == param.shape
        }


class TemperatureLearner:
    """Mixin of the soft algorithms: sets up, steps and logs the learned temperature of
    ``self.policy.temperature`` (an :class:`EntropyTemperature`).

    The algorithm provides ``policy`` (with ``temperature``, ``n_groups`` and ``action_counts``, the
    action count of every group), ``logger`` and the options ``alpha_init``, ``target_entropy_ratio``,
    ``learn_alpha``, ``alpha_optimizer`` and ``alpha_learning_rate``.
    """

    policy: Any
    logger: Any
    replay_buffer: Any
    alpha_init: float | str
    target_entropy_ratio: float
    learn_alpha: bool
    alpha_optimizer: str
    alpha_learning_rate: float
    alpha_max_step: float
    _n_updates: int

    def _set_temperature_options(
        self,
        target_entropy_ratio: float,
        alpha_init: float | str,
        learn_alpha: bool,
        alpha_optimizer: str,
        alpha_learning_rate: float,
        alpha_max_step: float,
    ) -> None:
        """Check and keep the temperature options (see the algorithms' parameters)."""
        check_alpha_init(alpha_init)
        check_max_step_ratio(alpha_max_step)
        self.target_entropy_ratio = target_entropy_ratio
        self.alpha_init = alpha_init
        self.learn_alpha = learn_alpha
        self.alpha_optimizer = alpha_optimizer
        self.alpha_learning_rate = alpha_learning_rate
        self.alpha_max_step = alpha_max_step

    def _setup_temperature(self) -> None:
        """Reset alpha to ``alpha_init`` (:data:`FALLBACK_ALPHA` until the first gradient step with
        ``"auto"``) and build the controller toward every group's target entropy."""
        self.policy.temperature.reset(FALLBACK_ALPHA if self.alpha_init == AUTO_ALPHA else self.alpha_init)
        self.target_entropy = [
            target_entropy(self.target_entropy_ratio, n) for n in self.policy.action_counts
        ]
        self.temperature = TemperatureController(
            self.policy.temperature,
            th.tensor(self.target_entropy),
            self.alpha_optimizer,
            self.alpha_learning_rate,
            max_step_ratio=self.alpha_max_step,
        )

    def _stored_rewards(self) -> np.ndarray:
        """The rewards in the replay buffer (SB3's or the graph one), those of agents gone before
        they acted left out: ``(n_stored, ...)`` or flat."""
        buffer = self.replay_buffer
        rows = slice(None) if buffer.full else slice(0, buffer.pos)
        alive = getattr(buffer, "alive", None)
        return buffer.rewards[rows] if alive is None else buffer.rewards[rows][alive[rows]]

    def _start_temperature(self) -> None:
        """Before the first gradient step of a model with ``alpha_init="auto"``: set alpha from the
        stored rewards (:func:`alpha_from_rewards`). Later calls, and resumed models, change nothing."""
        if self.alpha_init == AUTO_ALPHA and self._n_updates == 0:
            self.policy.temperature.reset(alpha_from_rewards(self._stored_rewards()))

    def _learns_alpha(self) -> bool:
        """Whether training steps alpha (``learn_alpha``)."""
        return self.learn_alpha

    def _update_temperature(
        self, entropy: th.Tensor, groups: th.Tensor | None, alive: th.Tensor
    ) -> tuple[th.Tensor, th.Tensor | None]:
        """Measure the mean policy entropy of every group from the per-agent entropies
        ``(batch, n_agents)`` (or ``(batch,)``) of the living agents (``alive``, same shape, 1 or 0)
        and step alpha toward the targets; returns the group entropies ``(n_groups,)`` and alpha's
        mean gradient ``()`` (``None`` when alpha is not learned), both left on the device."""
        group_entropy = group_means(entropy.detach(), groups, self.policy.n_groups, alive)
        gradient = self.temperature.update(group_entropy) if self._learns_alpha() else None
        return group_entropy, gradient

    def _record_temperature(self, entropies: list[th.Tensor], alpha_gradients: list[th.Tensor]) -> None:
        """Log the mean policy entropy of the last training round, its target, alpha and its gradient
        (averaged over groups, and per group ``g`` as ``.../group_g`` with several groups)."""
        entropy = th.stack(entropies).nanmean(dim=0).cpu().numpy()
        alpha = self.policy.temperature.alpha.detach().cpu().numpy()
        figures = {"entropy": entropy, "target_entropy": np.array(self.target_entropy), "alpha": alpha}
        for name, values in figures.items():
            self.logger.record(f"train/{name}", float(np.nanmean(values)))
            if len(values) > 1:
                for group, value in enumerate(values):
                    self.logger.record(f"train/{name}/group_{group}", float(value))
        if alpha_gradients:
            self.logger.record("train/alpha_grad", float(th.stack(alpha_gradients).mean()))
