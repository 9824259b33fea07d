"""Vectorised checks of the arrays a graph VecEnv hands out and ``predict`` takes: observations,
neighbour indices, rewards and recurrent states.

They run on numpy arrays before anything reaches torch, one pass over each array, so a bad value is
reported with the slot it came from instead of surfacing later as a torch error or a silent ``nan``.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from gymnasium import spaces

MAX_ABS_REWARD = 1e12
"""The largest reward magnitude the algorithms accept. With it a return over a horizon of up to
``1 / (1 - gamma) = 1000`` steps stays within 1e15, a TD error within 2e15 and its square within 4e30,
so the summed squared errors of a batch of up to 1e7 agent-transitions (4e37) stay below float32's
largest value, 3.4e38; larger rewards would turn the losses and then the parameters into inf and
``nan``."""


def slot_name(slot: int, n_agents: int) -> str:
    """``agent a of env copy c (slot s)`` for a slot of the copy-major layout."""
    return f"agent {slot % n_agents} of env copy {slot // n_agents} (slot {slot})"


def _first_bad_row(bad: np.ndarray) -> tuple[int, int]:
    """``(row, column)`` of the first true entry of a ``(n_slots, width)`` mask."""
    row = int(np.flatnonzero(bad.any(axis=1))[0])
    return row, int(np.flatnonzero(bad[row])[0])


def observation_problem(
    observations: Mapping[str, np.ndarray], obs_space: spaces.Box, n_agents: int
) -> tuple[int, str] | None:
    """The first slot with a bad observation and what is wrong with it, ``None`` if all are good.

    An observation is bad when a value of ``obs`` is NaN or infinite or lies outside ``obs_space``'s
    bounds, or a neighbour index is not a whole number or lies outside ``[-1, n_agents - 1]``.

    :param observations: ``{"obs": (n_slots, *obs_shape), "neighbors": (n_slots, K), ...}``; the
        problem names a value of an n-D observation by its index tuple.
    :param obs_space: the ``Box`` of one agent's ``obs``.
    :param n_agents: agents per env copy.
    :return: ``(slot, problem)`` or ``None``.
    """
    obs = np.asarray(observations["obs"])
    inside = (obs >= obs_space.low) & (obs <= obs_space.high)
    if obs.dtype.kind == "f":
        inside &= np.isfinite(obs)
    if not inside.all():
        slot, index = _first_bad_row(~inside.reshape(len(obs), -1))
        value = obs.reshape(len(obs), -1)[slot, index]
        where = index if obs.ndim == 2 else tuple(int(i) for i in np.unravel_index(index, obs.shape[1:]))
        if not np.isfinite(value):
            return slot, f"the non-finite value {value} at obs index {where}"
        low, high = obs_space.low.reshape(-1)[index], obs_space.high.reshape(-1)[index]
        return slot, f"the value {value} at obs index {where}, outside the observation space [{low}, {high}]"
    neighbors = np.asarray(observations["neighbors"])
    if neighbors.dtype.kind not in "iu":
        whole = np.isfinite(neighbors) & (neighbors == np.round(neighbors))
        if not whole.all():
            slot, index = _first_bad_row(~whole)
            return slot, f"the neighbour index {neighbors[slot, index]}, not a whole number"
    valid = (neighbors >= -1) & (neighbors < n_agents)
    if not valid.all():
        slot, index = _first_bad_row(~valid)
        return slot, (
            f"the neighbour index {neighbors[slot, index]}, not one of the agent indices in "
            f"[-1, {n_agents - 1}] (within the copy, -1 for none)"
        )
    return None


def check_rewards(rewards: np.ndarray, n_agents: int, when: str) -> None:
    """Raise a ``ValueError`` naming the first slot with a NaN or infinite reward or one whose magnitude
    exceeds :data:`MAX_ABS_REWARD`.

    :param rewards: ``(n_slots,)`` rewards of one vec-step.
    :param n_agents: agents per env copy.
    :param when: the step, as the message should name it (``"at agent-step 120"``).
    """
    finite = np.isfinite(rewards)
    if not finite.all():
        slot = int(np.flatnonzero(~finite)[0])
        raise ValueError(
            f"The env returned non-finite rewards: {rewards[slot]} for {slot_name(slot, n_agents)} {when} "
            f"({int((~finite).sum())} of {len(rewards)} slots)."
        )
    bounded = np.abs(rewards) <= MAX_ABS_REWARD
    if not bounded.all():
        slot = int(np.flatnonzero(~bounded)[0])
        raise ValueError(
            f"The env returned rewards beyond the bound |reward| <= {MAX_ABS_REWARD:g}: {rewards[slot]:g} "
            f"for {slot_name(slot, n_agents)} {when} ({int((~bounded).sum())} of {len(rewards)} slots); "
            "scale the env's rewards down (docs/reliability.md, 'Rewards')."
        )


def check_numbers(array: np.ndarray, name: str) -> None:
    """Raise a ``TypeError`` naming ``name`` unless ``array`` holds real numbers (bool, int or float)."""
    if array.dtype.kind not in "biuf":
        raise TypeError(f"{name} must hold numbers, got dtype {array.dtype}.")


def check_graph_batch(observation: Any, observation_space: spaces.Dict) -> None:
    """Raise an error saying what is expected unless ``observation`` is a slot batch of the graph
    VecEnv whose observation space is ``observation_space``: a mapping with each of its keys, whose
    arrays hold numbers with the shape ``(n_slots, *shape)`` of the key's space (``n_slots`` from
    ``obs``).

    :param observation: what ``predict`` was given.
    :param observation_space: Dict space with ``obs`` and ``neighbors`` (and ``group``, ``action_mask``).
    """
    keys = ["obs", "neighbors", *(key for key in observation_space.spaces if key not in ("obs", "neighbors"))]
    listed = " and ".join([", ".join(map(repr, keys[:-1])), repr(keys[-1])])
    if not isinstance(observation, Mapping):
        given = (
            f"an array of shape {observation.shape}"
            if isinstance(observation, np.ndarray)
            else f"a {type(observation).__name__}"
        )
        raise TypeError(
            f"observation must be a dict with the keys {listed}, each an array with one "
            f"row per slot of the graph VecEnv (as its reset() and step() return), got {given}."
        )
    missing = [key for key in keys if key not in observation]
    if missing:
        raise ValueError(
            f"observation lacks the key {missing[0]!r}; a graph observation has the keys {listed}."
        )
    arrays = {key: np.asarray(observation[key]) for key in keys}
    if arrays["obs"].shape == observation_space["obs"].shape:
        raise ValueError(
            "predict() takes the observations of all slots of a graph VecEnv (a batch), not the "
            "observation of a single agent."
        )
    n_slots = arrays["obs"].shape[0] if arrays["obs"].ndim else 0
    for key, array in arrays.items():
        check_numbers(array, f"observation[{key!r}]")
        shape = observation_space[key].shape
        if array.shape != (n_slots, *shape):
            expected = ["n_slots" if key == "obs" else str(n_slots), *map(str, shape)]
            raise ValueError(
                f"observation[{key!r}] has shape {array.shape}, expected ({', '.join(expected)}"
                f"{',' if len(expected) == 1 else ''})."
            )


def check_state(hidden: np.ndarray, n_agents: int) -> None:
    """Raise an error naming the first slot unless the recurrent state ``hidden`` ``(n_slots,
    state_dim)`` holds finite numbers (``TypeError`` for another dtype, ``ValueError`` for NaN or inf)."""
    check_numbers(hidden, "state[0]")
    finite = np.isfinite(hidden)
    if not finite.all():
        slot, index = _first_bad_row(~finite)
        raise ValueError(
            f"state[0] holds the non-finite value {hidden[slot, index]} for {slot_name(slot, n_agents)} "
            f"(state index {index}); pass the state the previous predict() returned, or None to start "
            "from zeros."
        )
