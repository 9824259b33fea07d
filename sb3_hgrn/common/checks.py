"""Vectorised checks of the arrays a graph VecEnv hands out: observations, neighbour indices, rewards.

They run on numpy arrays before anything reaches torch, one pass over each array, so a bad value is
reported with the slot it came from instead of surfacing later as a torch error or a silent ``nan``.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from gymnasium import spaces


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
    """Raise a ``ValueError`` naming the first slot with a NaN or infinite reward.

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
