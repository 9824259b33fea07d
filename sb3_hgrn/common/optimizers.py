"""Optimiser options every algorithm's policy builds its network optimisers with."""

from __future__ import annotations

from typing import Any

import torch as th


def fused_by_default(
    optimizer_class: type[th.optim.Optimizer], optimizer_kwargs: dict[str, Any] | None
) -> dict[str, Any]:
    """``optimizer_kwargs`` with ``fused=True`` added for ``Adam`` and ``AdamW`` when they name neither
    ``fused`` nor ``foreach``: one kernel then steps every parameter, where torch's default on the
    CPU loops over them in Python, a large share of a gradient step on small networks."""
    optimizer_kwargs = dict(optimizer_kwargs or {})
    named = {"fused", "foreach"} & set(optimizer_kwargs)
    if optimizer_class in (th.optim.Adam, th.optim.AdamW) and not named:
        optimizer_kwargs["fused"] = True
    return optimizer_kwargs
