"""Type checks of keyword arguments against the annotations of the function that takes them.

Only the plain number and flag types are checked (``int``, ``float``, ``bool``, each possibly ``| None``):
a value of another type there would otherwise surface far away as a comparison between a ``str`` and
an ``int``. Arguments annotated with anything else are left to the code that uses them.
"""

from __future__ import annotations

import inspect
import types
import typing
from collections.abc import Callable, Mapping
from typing import Any

from sb3_hgrn.validation import is_flag, is_integer, is_number

EXPECTED = {int: "an integer", float: "a number", bool: "true or false", type(None): "None"}
"""The checked types and how a message names them."""


MATCHES: dict[type, Callable[[Any], bool]] = {
    int: is_integer,
    float: is_number,
    bool: is_flag,
    type(None): lambda value: value is None,
}


def checked_types(hint: Any) -> tuple[type, ...] | None:
    """The types an annotation allows when all of them are checked ones (see :data:`EXPECTED`), else
    ``None`` (the argument is not checked)."""
    union = isinstance(hint, types.UnionType) or typing.get_origin(hint) is typing.Union
    allowed = typing.get_args(hint) if union else (hint,)
    return allowed if all(kind in EXPECTED for kind in allowed) else None


def argument_hints(function: Callable[..., Any]) -> dict[str, tuple[type, ...]]:
    """The checked types of every checked parameter of ``function`` (see :func:`checked_types`); an
    annotation that names something its module cannot resolve is not checked."""
    hints = {}
    for name, parameter in inspect.signature(function).parameters.items():
        hint = parameter.annotation
        if isinstance(hint, str):  # postponed (``from __future__ import annotations``)
            try:
                hint = eval(hint, function.__globals__)  # what typing.get_type_hints does, per argument
            except (NameError, TypeError, AttributeError):
                continue
        allowed = checked_types(hint)
        if allowed is not None:
            hints[name] = allowed
    return hints


def check_argument_types(
    hints: Mapping[str, tuple[type, ...]], arguments: Mapping[str, Any], prefix: str = ""
) -> None:
    """Raise a ``TypeError`` naming the first argument whose value has none of its allowed types.

    :param hints: the allowed types per argument name (:func:`argument_hints`); others are not checked.
    :param arguments: argument values by name.
    :param prefix: put before the name in the message (``"policy_kwargs."``).
    """
    for name, value in arguments.items():
        allowed = hints.get(name)
        if allowed is not None and not any(MATCHES[kind](value) for kind in allowed):
            expected = " or ".join(EXPECTED[kind] for kind in allowed)
            raise TypeError(f"{prefix}{name} must be {expected}, got {value!r}.")


def named_parameters(function: Callable[..., Any]) -> list[str]:
    """The names of ``function``'s parameters other than ``self``, ``*args`` and ``**kwargs``."""
    return [
        name
        for name, parameter in inspect.signature(function).parameters.items()
        if name != "self" and parameter.kind not in (parameter.VAR_POSITIONAL, parameter.VAR_KEYWORD)
    ]
