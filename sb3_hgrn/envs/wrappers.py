"""PettingZoo wrappers that make third-party many-agent envs into graph envs.

:class:`GraphFromPositions` gives any ``ParallelEnv`` the ``neighbors()`` method and
``max_neighbors`` attribute that :func:`sb3_hgrn.make_graph_vec_env` needs, from the agents'
positions. :func:`as_parallel_env` turns a PettingZoo AEC env whose agents act simultaneously into a
``ParallelEnv``.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from pettingzoo import AECEnv, ParallelEnv
from pettingzoo.utils import BaseParallelWrapper
from pettingzoo.utils.conversions import aec_to_parallel

from sb3_hgrn.envs.position_graph import PositionGraph


def as_parallel_env(env: ParallelEnv | AECEnv) -> ParallelEnv:
    """``env`` as a PettingZoo ``ParallelEnv``; an AEC env is converted with PettingZoo's
    ``aec_to_parallel`` when its metadata declares ``is_parallelizable``.

    Raises a ``TypeError`` naming what to pass instead for a turn-based AEC env or a non-PettingZoo
    object.
    """
    if isinstance(env, ParallelEnv):
        return env
    if isinstance(env, AECEnv):
        if not env.metadata.get("is_parallelizable", False):
            raise TypeError(
                f"{type(env).__name__} is a PettingZoo AEC env whose metadata does not declare "
                "is_parallelizable=True, so its agents may act in turn; sb3_hgrn steps every agent at "
                "once. Pass the env's ParallelEnv instead (PettingZoo modules offer parallel_env())."
            )
        return aec_to_parallel(env)
    raise TypeError(f"Expected a PettingZoo ParallelEnv or AEC env, got {type(env).__name__}.")


class GraphFromPositions(BaseParallelWrapper):
    """A ``ParallelEnv`` whose communication graph links agents by their positions.

    Wrap any PettingZoo env with it to use it with :func:`sb3_hgrn.make_graph_vec_env`::

        env = GraphFromPositions(my_env, positions=lambda env: env.agent_xy, k=4)

    Every step (and after ``reset``) ``positions(env)`` is called once, when the graph is first
    asked for, with the env given here, and must return the agents' float positions
    ``(n_agents, dim)`` in ``possible_agents`` order (any ``dim >= 1``). Distances are Euclidean.

    Args:
        env: the PettingZoo ``ParallelEnv`` (or parallelizable AEC env, see :func:`as_parallel_env`).
        positions: ``positions(env) -> (n_agents, dim)`` float array.
        k: link each agent to its ``k`` nearest other agents; the lists are ``k + 1`` wide.
        radius: link each agent to every other agent at distance ``<= radius``, the nearest
            ``max_neighbors - 1`` of them where there are more.
        max_neighbors: the list width in radius mode, the agent itself included (required there).
        world_size: the side of a toroidal world (one for all axes, or one per axis): positions are
            wrapped and distances taken the shortest way round. ``None``: no wrap.

    With neither ``k`` nor ``radius`` every agent lists every agent (the full graph, ``n_agents``
    wide, quadratic in the agent count: meant for small teams). The ``k`` and radius modes use a
    KD-tree and cost near-linear time in the agent count (``benchmarks/graph_from_positions.py``).

    Attributes:
        max_neighbors: width of the neighbour lists, the agent itself included.
        graph: the :class:`~sb3_hgrn.envs.position_graph.PositionGraph` that builds them.
    """

    def __init__(
        self,
        env: ParallelEnv | AECEnv,
        positions: Callable[[Any], np.ndarray],
        k: int | None = None,
        radius: float | None = None,
        max_neighbors: int | None = None,
        world_size: float | Sequence[float] | None = None,
    ):
        if not callable(positions):
            raise TypeError(
                f"positions must be a callable taking the env and returning (n_agents, dim) "
                f"positions, got {type(positions).__name__}."
            )
        super().__init__(as_parallel_env(env))
        self.graph = PositionGraph(len(self.env.possible_agents), k, radius, max_neighbors, world_size)
        self.max_neighbors = self.graph.max_neighbors
        self._positions = functools.partial(positions, env)
        self._lists: np.ndarray | None = None

    def reset(self, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        self._lists = None
        return self.env.reset(seed=seed, options=options)

    def step(self, actions: dict) -> tuple[dict, dict, dict, dict, dict]:
        self._lists = None
        return self.env.step(actions)

    def neighbors(self) -> np.ndarray:
        """Graph of the current positions: ``(n_agents, max_neighbors)`` int64, read-only.

        Row ``i`` is agent ``i`` itself, then its neighbours nearest first, ``-1`` pads (see
        :meth:`PositionGraph.neighbors`); built at most once per step.
        """
        if self._lists is None:
            lists = self.graph.neighbors(self._positions())
            lists.flags.writeable = False
            self._lists = lists
        return self._lists
