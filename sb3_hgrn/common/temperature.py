"""Learned temperature that keeps a policy's action entropy at a target, shared by the soft algorithms.

The target is ``target_entropy_ratio * log(n_actions)``. After each critic step the mean policy
entropy ``H`` of the batch is measured and alpha takes one optimiser step on
``loss = alpha * (H - H_target)``: its gradient ``H - H_target`` lowers alpha while the policy is
more random than the target and raises it while the policy is too greedy. As in the paper, the
gradient is clipped to ``max_grad_ratio * alpha`` in magnitude and alpha stays above ``min_alpha``.
"""

from __future__ import annotations

import math

import torch as th
from torch import nn

ALPHA_OPTIMIZERS = {"adam": th.optim.Adam, "sgd": th.optim.SGD}


class EntropyTemperature(nn.Module):
    """The temperature alpha as a learnable parameter (raw alpha, or its log with ``log_space``).

    It lives in the policy, so it is saved with the policy and ``predict`` can sample from
    ``softmax(Q / alpha)``.
    """

    def __init__(self, initial_alpha: float = 0.1, log_space: bool = False):
        super().__init__()
        if initial_alpha <= 0:
            raise ValueError(f"initial_alpha must be > 0, got {initial_alpha}.")
        self.log_space = log_space
        value = math.log(initial_alpha) if log_space else initial_alpha
        self.param = nn.Parameter(th.tensor(float(value)))

    @property
    def alpha(self) -> th.Tensor:
        """Scalar alpha > 0 (carries gradient to ``param``)."""
        return self.param.exp() if self.log_space else self.param


def target_entropy(ratio: float, n_actions: int) -> float:
    """Target entropy ``ratio * log(n_actions)`` in nats; ``ratio`` must lie in [0, 1]."""
    if not 0.0 <= ratio <= 1.0:
        raise ValueError(f"target_entropy_ratio must be within [0, 1], got {ratio}.")
    return ratio * math.log(n_actions)


def categorical_entropy(logits: th.Tensor) -> th.Tensor:
    """Entropy in nats of ``softmax(logits)`` along the last axis: ``(...)`` from ``(..., n_actions)``."""
    log_probs = th.log_softmax(logits, dim=-1)
    return -(log_probs.exp() * log_probs).sum(dim=-1)


class TemperatureController:
    """Optimises an :class:`EntropyTemperature` toward a target entropy.

    :param temperature: the policy's temperature module.
    :param target: target entropy in nats.
    :param optimizer: ``"adam"`` or ``"sgd"``.
    :param learning_rate: learning rate of that optimiser.
    :param max_grad_ratio: gradients are clipped to ``max_grad_ratio * alpha`` in magnitude.
    :param min_alpha: lower bound of alpha.
    """

    def __init__(
        self,
        temperature: EntropyTemperature,
        target: float,
        optimizer: str = "adam",
        learning_rate: float = 1e-3,
        max_grad_ratio: float = 0.01,
        min_alpha: float = 1e-5,
    ):
        if optimizer not in ALPHA_OPTIMIZERS:
            raise ValueError(f"alpha_optimizer must be one of {sorted(ALPHA_OPTIMIZERS)}, got {optimizer!r}.")
        self.temperature = temperature
        self.target = target
        self.max_grad_ratio = max_grad_ratio
        self.min_alpha = min_alpha
        self.optimizer = ALPHA_OPTIMIZERS[optimizer]([temperature.param], lr=learning_rate)

    def update(self, entropy: th.Tensor) -> float:
        """One step toward the target given the measured mean entropy; returns alpha's gradient."""
        self.optimizer.zero_grad()
        loss = self.temperature.alpha * (entropy.detach() - self.target)
        loss.backward()
        gradient = float(self.temperature.param.grad)
        bound = self.max_grad_ratio * float(self.temperature.alpha.detach())
        if self.temperature.log_space:
            bound = self.max_grad_ratio  # a step in log(alpha) is already relative: clip it to the ratio
        self.temperature.param.grad.clamp_(-bound, bound)
        self.optimizer.step()
        with th.no_grad():
            if self.temperature.log_space:
                self.temperature.param.clamp_(min=math.log(self.min_alpha))
            else:
                self.temperature.param.clamp_(min=self.min_alpha)
        return gradient
