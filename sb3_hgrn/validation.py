"""Checks of plain argument values (integers, numbers, flags), shared by both halves of the package.

The env side (:mod:`sb3_hgrn.envs`) and the learner side take them from here: this module imports
numpy only, so the env side stays free of torch and of learner code.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np


def is_integer(value: Any) -> bool:
    """Whether ``value`` is a Python or numpy integer (not a bool)."""
    return isinstance(value, int | np.integer) and not isinstance(value, bool)


def is_number(value: Any) -> bool:
    """Whether ``value`` is a Python or numpy integer or float (not a bool)."""
    return isinstance(value, int | float | np.integer | np.floating) and not isinstance(value, bool)


def is_flag(value: Any) -> bool:
    """Whether ``value`` is ``True`` or ``False`` (a Python or numpy bool)."""
    return isinstance(value, bool | np.bool_)


def check_integer(name: str, value: Any, low: int, high: int | None = None, why: str = "") -> None:
    """Raise a ``ValueError`` naming ``name``, the valid range and ``value`` unless ``value`` is a
    Python or numpy integer (not a bool) in ``low..high`` (``>= low`` when ``high`` is ``None``);
    ``why`` says where the bounds come from."""
    if is_integer(value) and low <= value and (high is None or value <= high):
        return
    valid = f">= {low}" if high is None else f"in {low}..{high}"
    raise ValueError(f"{name} must be an integer {valid}{f' ({why})' if why else ''}, got {value!r}.")


def check_number(name: str, value: Any, low: float | None = None, strict: bool = False) -> None:
    """Raise a ``ValueError`` naming ``name``, the valid range and ``value`` unless ``value`` is a real
    number (not a bool, not NaN) ``>= low`` (``> low`` when ``strict``; any when ``low`` is ``None``)."""
    if (
        is_number(value)
        and not math.isnan(value)
        and (low is None or (value > low if strict else value >= low))
    ):
        return
    valid = "" if low is None else f" {'>' if strict else '>='} {low}"
    raise ValueError(f"{name} must be a number{valid}, got {value!r}.")


def check_flag(name: str, value: Any) -> None:
    """Raise a ``ValueError`` naming ``name`` and ``value`` unless ``value`` is ``True`` or ``False``
    (a string such as ``"no"`` would otherwise count as true)."""
    if not is_flag(value):
        raise ValueError(f"{name} must be true or false, got {value!r}.")
