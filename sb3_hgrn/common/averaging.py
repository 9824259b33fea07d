"""Polyak averages of a network's weights, on torch's :class:`~torch.optim.swa_utils.AveragedModel`."""

from __future__ import annotations

from typing import Any

import torch as th
from torch import nn
from torch.optim.swa_utils import AveragedModel


class PolyakWeight:
    """``multi_avg_fn`` of :class:`~torch.optim.swa_utils.AveragedModel`:
    ``average <- (1 - w) average + w current`` with the weight ``w = max(tau, 1 / (1 + n / window))``
    after ``n`` averaged iterates (the first iterate is copied).

    The weight falls with the number of updates, so the average covers about the last ``window``
    fraction of them (the last tenth by default) until that span reaches ``1 / tau`` updates, and
    then the last ``1 / tau``: early in training it follows the online network closely and never
    weighs on the first iterates (a fresh network's weights) for long, however short the run. The
    weight is computed on the device, from the count that ``AveragedModel`` keeps there, and every
    tensor of a device is updated in one multi-tensor (``torch._foreach``) operation per step.
    """

    def __init__(self, tau: float, window: float = 0.1):
        if not 0 < tau <= 1:
            raise ValueError(f"The averaging weight tau must be in (0, 1], got {tau}.")
        if not 0 < window <= 1:
            raise ValueError(f"The averaging window must be a fraction in (0, 1], got {window}.")
        self.tau = tau
        self.window = window

    def __call__(self, averaged: list[th.Tensor], current: list[th.Tensor], n_averaged: th.Tensor) -> None:
        """Move every tensor of ``averaged`` towards its counterpart in ``current``, in place."""
        weight = (1.0 / (1.0 + n_averaged * self.window)).clamp(min=self.tau)
        steps = th._foreach_sub(current, averaged)
        th._foreach_mul_(steps, weight)
        th._foreach_add_(averaged, steps)


class PolyakAverage(AveragedModel):
    """An :class:`~torch.optim.swa_utils.AveragedModel` of :class:`PolyakWeight` whose update never
    waits for the device.

    ``AveragedModel.update_parameters`` reads its count ``n_averaged`` (a device tensor) on the host
    twice per call, to copy the first iterate and to average the later ones, which makes the host
    wait for the device at every gradient step. Here whether the next update is the first is a
    Python flag, set when the average is made and whenever a state dict is loaded into it (one read of
    the count per load); the update runs the same tensor operations as ``AveragedModel``'s, so the
    averages are bitwise the same. Its state dict is ``AveragedModel``'s (``module.*``,
    ``n_averaged``).
    """

    def __init__(self, network: nn.Module, tau: float):
        super().__init__(network, multi_avg_fn=PolyakWeight(tau))
        self.copies_next = True
        self._listed: tuple[nn.Module, list[list[th.Tensor]]] | None = None
        self.register_load_state_dict_post_hook(PolyakAverage._count_loaded)

    def _tensors(self, model: nn.Module) -> list[list[th.Tensor]]:
        """The averaged parameters, ``model``'s, the averaged buffers and ``model``'s, listed once
        per ``model``: walking the modules costs about as much as the update itself on networks of
        several agent groups. The lists hold the tensor objects themselves, which ``to()`` and
        ``load_state_dict`` update in place."""
        if self._listed is None or self._listed[0] is not model:
            tensors = [
                list(self.module.parameters()),
                list(model.parameters()),
                list(self.module.buffers()),
                list(model.buffers()),
            ]
            if len(tensors[0]) != len(tensors[1]) or len(tensors[2]) != len(tensors[3]):
                raise ValueError("The averaged network and the given one hold different tensors.")
            self._listed = (model, tensors)
        return self._listed[1]

    @th.no_grad()
    def update_parameters(self, model: nn.Module) -> None:
        """Average ``model``'s parameters in (the first call copies them) and copy its buffers."""
        averaged, current, own_buffers, their_buffers = self._tensors(model)
        if self.copies_next:
            th._foreach_copy_(averaged, current)
        else:
            self.multi_avg_fn(averaged, current, self.n_averaged)
        if own_buffers:
            th._foreach_copy_(own_buffers, their_buffers)
        self.n_averaged += 1
        self.copies_next = False

    @staticmethod
    def _count_loaded(average: PolyakAverage, incompatible_keys: Any) -> None:
        """After a state dict is loaded: the next update is the first where the loaded count is 0."""
        average.copies_next = bool(average.n_averaged == 0)


def polyak_average(network: nn.Module, tau: float) -> PolyakAverage:
    """An untrained :class:`PolyakAverage` of ``network``; its ``update_parameters(network)`` after
    each gradient step keeps the average of :class:`PolyakWeight`."""
    average = PolyakAverage(network, tau)
    average.requires_grad_(False)
    average.train(False)
    return average
