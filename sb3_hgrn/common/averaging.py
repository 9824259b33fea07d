"""Polyak averages of a network's weights, on torch's :class:`~torch.optim.swa_utils.AveragedModel`."""

from __future__ import annotations

import torch as th
from torch import nn
from torch.optim.swa_utils import AveragedModel


class PolyakWeight:
    """``multi_avg_fn`` of :class:`~torch.optim.swa_utils.AveragedModel`: the plain mean of the first
    ``1 / tau`` iterates, then ``average <- (1 - tau) average + tau current``.

    Starting as a plain mean keeps the first iterates (a fresh network's weights) from weighing on
    the average for about ``1 / tau`` updates. The weight is computed on the device, from the
    count that ``AveragedModel`` keeps there, and every tensor of a device is updated in one
    multi-tensor (``torch._foreach``) operation per step.
    """

    def __init__(self, tau: float):
        if not 0 < tau <= 1:
            raise ValueError(f"The averaging weight tau must be in (0, 1], got {tau}.")
        self.tau = tau

    def __call__(self, averaged: list[th.Tensor], current: list[th.Tensor], n_averaged: th.Tensor) -> None:
        """Move every tensor of ``averaged`` towards its counterpart in ``current``, in place."""
        weight = (1.0 / (n_averaged + 1)).clamp(min=self.tau)
        steps = th._foreach_sub(current, averaged)
        th._foreach_mul_(steps, weight)
        th._foreach_add_(averaged, steps)


def polyak_average(network: nn.Module, tau: float) -> AveragedModel:
    """An untrained :class:`~torch.optim.swa_utils.AveragedModel` of ``network``; its
    ``update_parameters(network)`` after each gradient step keeps the average of :class:`PolyakWeight`."""
    average = AveragedModel(network, multi_avg_fn=PolyakWeight(tau))
    average.requires_grad_(False)
    average.train(False)
    return average
