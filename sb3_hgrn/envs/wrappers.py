"""PettingZoo wrappers that make third-party many-agent envs into graph envs.

:class:`GraphFromPositions` gives any ``ParallelEnv`` the ``neighbors()`` method and
``max_neighbors`` attribute that :func:`sb3_hgrn.make_graph_vec_env` needs, from the agents'
positions. :class:`DrivenAgents` keeps some of an env's agents as its agents (the learners) and has
a controller drive the others. :class:`TeamFigures` reports figures of the team's episode (agents
left per side, targets reached) that :func:`sb3_hgrn.make_graph_vec_env` adds to its episode infos.
:func:`as_parallel_env` turns a PettingZoo AEC env whose agents act simultaneously into a
``ParallelEnv``.
"""

from __future__ import annotations

import functools
import numbers
from collections.abc import Callable, Collection, Mapping, Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from pettingzoo import AECEnv, ParallelEnv
from pettingzoo.utils import BaseParallelWrapper
from pettingzoo.utils.conversions import aec_to_parallel

from sb3_hgrn.envs.driven_sides import DrivenSide, make_controller
from sb3_hgrn.envs.graph import living_neighbors, subgraph
from sb3_hgrn.envs.position_graph import PositionGraph

PREVIEW = 6  # agent names an error message lists before "..."


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
    Only the agents in the env's ``agents`` list are linked: an agent that died or left takes no
    place in any list, its row of ``positions`` is not read (any value, ``nan`` included, will do)
    and its own list holds only itself.

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
        self._names = np.asarray(self.env.possible_agents)
        self._lists: np.ndarray | None = None

    def reset(self, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        self._lists = None
        return self.env.reset(seed=seed, options=options)

    def step(self, actions: dict) -> tuple[dict, dict, dict, dict, dict]:
        self._lists = None
        return self.env.step(actions)

    def neighbors(self) -> np.ndarray:
        """Graph of the current positions: ``(n_agents, max_neighbors)`` int64, read-only.

        Row ``i`` is agent ``i`` itself, then its living neighbours nearest first, ``-1`` pads (see
        :meth:`PositionGraph.neighbors`); built at most once per step.
        """
        if self._lists is None:
            lists = self.graph.neighbors(self._positions(), self._alive())
            lists.flags.writeable = False
            self._lists = lists
        return self._lists

    def _alive(self) -> np.ndarray | None:
        """``(n_agents,)`` bool: which possible agents are in the env's ``agents`` list; ``None``
        when all are."""
        agents = list(getattr(self.env, "agents", None) or ())
        if len(agents) == len(self._names):
            return None
        return np.isin(self._names, np.asarray(agents, dtype=self._names.dtype))


class TeamFigures(BaseParallelWrapper):
    """A ``ParallelEnv`` that reports figures of its episode, such as the agents left on each side.

    After every step ``figures(env)`` is called with the env given here and returns a dict of
    numbers by name; :meth:`team_info` gives the last one. The graph VecEnv of
    :func:`sb3_hgrn.make_graph_vec_env` reads it after each step and adds the one after an episode's
    last step to that episode's ``info["team_episode"]``, next to the team return ``r`` and the
    length ``l``; :func:`sb3_hgrn.evaluate_team_episodes` returns them::

        env = TeamFigures(DrivenAgents(battle, "red_"), lambda env: {"left": len(env.agents)})

    Everything else (agents, spaces, ``neighbors()`` where the wrapped env has one) is the wrapped env's.

    Args:
        env: the PettingZoo ``ParallelEnv`` (or parallelizable AEC env, see :func:`as_parallel_env`).
        figures: ``figures(env) -> {name: number}``, read once after every step.

    Raises:
        TypeError: ``figures`` is not callable, or (at a step) returns something other than a dict of
            real numbers by string name.
    """

    def __init__(self, env: ParallelEnv | AECEnv, figures: Callable[[Any], Mapping[str, float]]):
        if not callable(figures):
            raise TypeError(
                f"figures must be a callable taking the env and returning a dict of numbers by name, got "
                f"{type(figures).__name__}."
            )
        super().__init__(as_parallel_env(env))
        self._figures = functools.partial(figures, env)
        self._last: dict[str, float] = {}

    def reset(self, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        self._last = {}
        return self.env.reset(seed=seed, options=options)

    def step(self, actions: dict) -> tuple[dict, dict, dict, dict, dict]:
        results = self.env.step(actions)
        self._last = _figures(self._figures())
        return results

    def team_info(self) -> dict[str, float]:
        """The figures after the last step (empty after a reset), a new dict at every call."""
        return dict(self._last)


def _figures(figures: Any) -> dict[str, float]:
    """``figures`` as a dict, or a ``TypeError`` when it is not a mapping of real numbers by string name."""
    if not isinstance(figures, Mapping):
        raise TypeError(f"figures must return a dict of numbers by name, got {type(figures).__name__}.")
    for name, value in figures.items():
        if not isinstance(name, str) or not isinstance(value, numbers.Real):
            raise TypeError(
                f"figures must return real numbers by string name, got {name!r}: {type(value).__name__}."
            )
    return dict(figures)


class DrivenAgents(ParallelEnv):
    """A ``ParallelEnv`` of some of an env's agents, the learners, while a controller drives the others.

    For instance red learns and a controller plays blue in MAgent2's ``battle_v4``::

        env = DrivenAgents(battle, learners="red_", controller="random")

    Only the learners are this env's agents: ``possible_agents``, ``agents``, the spaces and every
    dict that ``reset`` and ``step`` return hold only them. At every step the controller chooses the
    actions of the driven agents still in the inner env's ``agents`` (a gone one is not asked), and
    the inner env steps with all actions at once.

    Controllers (see :mod:`sb3_hgrn.envs.driven_sides`):

    - ``"random"``: uniform actions from each driven agent's ``Discrete`` action space, drawn from
      this env's generator;
    - a function ``controller(observations, env) -> actions``: ``observations`` holds the living
      driven agents' observations by name, ``env`` is the inner env, and ``actions`` must hold one
      action for each of them (by name) and nothing else;
    - a model with SB3's ``predict`` (``sb3_hgrn.common.saved_controllers.ModelController`` of an sb3_hgrn
      model, or of a saved one's path, loaded on the learner side: this env loads no file). The
      driven agents form one graph, in the fixed slots of :attr:`driven_agents`: the model gets
      ``{"obs": (n_driven, *obs_shape), "neighbors": (n_driven, K) int32}``. A gone agent keeps its
      slot, with the last observation the model had of it and an all ``-1`` list, no list names it,
      and its action is dropped. The model's recurrent state is carried through the episode and reset at every
      ``reset``; its ``bind(observation_space, n_driven)`` is called once here and its
      ``seed(int)`` before every ``predict`` with a seed from this env's generator, where it has
      them. The driven agents must share one ``Box`` observation space.

    The model's neighbour lists come from ``controller_neighbors(env, names) -> (n, K)`` when it is
    given (``env`` the inner env, ``names`` the ``n`` living driven agents; row ``j`` lists
    positions in ``names``, row ``j`` itself first, ``-1`` pads); otherwise from the inner env's
    ``neighbors()`` (rows in its ``possible_agents`` order), cut down to the driven agents among
    themselves (:func:`~sb3_hgrn.envs.graph.subgraph`: entries naming learners become ``-1``). Lists
    narrower than the model's ``observation_space["neighbors"]`` are padded with ``-1``; wider ones
    are an error. A model with neither source is refused when this env is built.

    Self-play: the model trained on the learners drives the others when their spaces match, e.g.
    ``controller=ModelController("red.zip")`` for blue in battle.

    Graph of the learners: where the inner env has ``neighbors()`` and ``max_neighbors``, this env
    has them too, cut down to the learners (:func:`~sb3_hgrn.envs.graph.subgraph`); otherwise wrap
    this env in :class:`GraphFromPositions`.

    Episode end: the episode ends for the learners when none of them is left in the inner env's
    ``agents`` (their last dicts carry the inner env's terminations and truncations); this env
    then has no agents and refuses to ``step`` until ``reset``, so the inner env is never stepped
    after its episode ended. Driven agents all gone while learners remain: the episode goes on as
    the inner env decides, with the learners' actions only.

    Seeding: one numpy generator, reseeded by ``reset(seed=...)`` (the first reset without a seed
    seeds it from entropy; later unseeded resets continue it), drives the random controller and the
    seeds handed to a model; ``seed`` is passed on to the inner env's ``reset``.

    Args:
        env: the PettingZoo ``ParallelEnv`` (or parallelizable AEC env, see :func:`as_parallel_env`).
        learners: the learning agents: a collection of agent names, a name prefix such as ``"red_"``,
            or a predicate ``name -> bool``.
        controller: ``"random"``, a function or a model (see above).
        controller_neighbors: ``(env, names) -> (n, K)`` int array, the neighbour lists of a model
            controller's agents (see above).
        deterministic: greedy actions for a model controller.

    Attributes:
        driven_agents: the driven agents' names, in the model's slot order.
        controller: the controller as given.
        max_neighbors: width of :meth:`neighbors`' lists (only where the inner env has a graph).

    Raises:
        ValueError: ``learners`` names an agent the env does not have, or selects no agent or all
            of them; a string ``controller`` other than ``"random"``; a model controller without
            neighbour lists or over driven agents without one shared ``Box`` observation space.
        TypeError: a ``learners`` or ``controller`` of another kind, or ``"random"`` over a
            non-``Discrete`` action space.
    """

    def __init__(
        self,
        env: ParallelEnv | AECEnv,
        learners: Collection[str] | str | Callable[[str], bool],
        controller: Any = "random",
        controller_neighbors: Callable[[Any, list[str]], np.ndarray] | None = None,
        deterministic: bool = False,
    ) -> None:
        self.env = as_parallel_env(env)
        inner_agents = list(self.env.possible_agents)
        is_learner = _learner_mask(inner_agents, learners)
        if controller_neighbors is not None and not callable(controller_neighbors):
            raise TypeError(
                "controller_neighbors must be a callable (env, names) -> (n, K) int array, got "
                f"{type(controller_neighbors).__name__}."
            )
        self.possible_agents = [agent for agent, keep in zip(inner_agents, is_learner, strict=True) if keep]
        self.driven_agents = tuple(
            agent for agent, keep in zip(inner_agents, is_learner, strict=True) if not keep
        )
        self.agents: list[str] = []
        self.metadata = getattr(self.env, "metadata", {})
        self.render_mode = getattr(self.env, "render_mode", None)
        self._inner_index = {agent: i for i, agent in enumerate(inner_agents)}
        self._learner_rows = np.flatnonzero(is_learner)
        self._row_of_inner = np.full(len(inner_agents), -1, dtype=np.int64)
        self._row_of_inner[self._learner_rows] = np.arange(len(self._learner_rows))
        self._learner_set = frozenset(self.possible_agents)
        self._observation_spaces = {
            agent: self.env.observation_space(agent) for agent in self.possible_agents
        }
        self._action_spaces = {agent: self.env.action_space(agent) for agent in self.possible_agents}
        self._has_graph = callable(getattr(self.env, "neighbors", None))
        if self._has_graph:
            self.max_neighbors = int(self.env.max_neighbors)
        self._side = DrivenTeam(
            self.env, self.driven_agents, np.flatnonzero(~is_learner), controller_neighbors
        )
        self.controller = controller
        self._driver = make_controller(controller, self._side, deterministic=deterministic)

    def reset(self, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        self._side.reseed(seed)
        observations, infos = self.env.reset(seed=seed, options=options)
        self._driver.reset()
        self._update(observations)
        return self._of_learners(observations, self.agents), self._of_learners(infos, self.agents)

    def step(self, actions: dict) -> tuple[dict, dict, dict, dict, dict]:
        """Step the inner env with the learners' ``actions`` and the controller's.

        :raises RuntimeError: when no learner is left (call ``reset``); the inner env is not stepped.
        :raises ValueError: for an action of an agent that is not a learner.
        """
        acting = self.agents
        if not acting:
            raise RuntimeError(
                "No learner is left in this episode (their episode is over), so the inner env was not "
                "stepped; call reset() first."
            )
        if not self._learner_set.issuperset(actions):
            others = [agent for agent in actions if agent not in self._learner_set]
            raise ValueError(f"Only learners act in a DrivenAgents env; got actions for {others[:PREVIEW]}.")
        all_actions = dict(actions)
        if self._side.living_names:
            all_actions.update(zip(self._side.living_names, self._driver.actions(self._side), strict=True))
        results = self.env.step(all_actions)
        self._update(results[0])
        return tuple(self._of_learners(result, acting) for result in results)

    def _update(self, observations: dict) -> None:
        """Read who is left in the inner env after a reset or step."""
        index = self._inner_index
        present = np.zeros(len(index), dtype=bool)
        try:
            present[[index[agent] for agent in self.env.agents]] = True
        except KeyError as error:
            raise ValueError(
                f"{type(self.env).__name__} reports the agent {error.args[0]!r}, which is not in its "
                "possible_agents."
            ) from None
        self.agents = [self.possible_agents[i] for i in np.flatnonzero(present[self._learner_rows])]
        self._side.update(observations, present)

    def learner_rows_of(self, inner_indices: Any) -> np.ndarray:
        """Rows in this env's ``possible_agents`` of the inner env's agents at ``inner_indices``.

        For engines that number agents by their index in the inner env's ``possible_agents`` (as
        MAgent2's ``get_agent_id`` does: red, then blue), where the learners need not come first.

        :param inner_indices: ``(n,)`` integer positions in the inner env's ``possible_agents``.
        :return: ``(n,)`` int64: each agent's row in this env's ``possible_agents`` (the learners in
            the inner order), ``-1`` for a driven agent.
        :raises ValueError: for an index that is not an integer in ``[0, len(inner possible_agents))``.
        """
        indices = np.asarray(inner_indices)
        if indices.size == 0:
            return np.zeros(indices.shape, dtype=np.int64)
        n_inner = len(self._row_of_inner)
        integral = indices.dtype.kind in "iu"
        if not integral or indices.min() < 0 or indices.max() >= n_inner:
            wrong = indices[(indices < 0) | (indices >= n_inner)] if integral else indices
            raise ValueError(
                f"inner_indices must be integers in [0, {n_inner}) (positions in the inner env's "
                f"possible_agents), got {wrong.ravel()[:PREVIEW].tolist()}."
            )
        return self._row_of_inner[indices]

    @staticmethod
    def _of_learners(values: dict, agents: list[str]) -> dict:
        """The entries of ``values`` of the agents ``agents``."""
        return {agent: values[agent] for agent in agents if agent in values}

    def observation_space(self, agent: str) -> gym.Space:
        return self._learner_space(self._observation_spaces, agent)

    def action_space(self, agent: str) -> gym.Space:
        return self._learner_space(self._action_spaces, agent)

    def _learner_space(self, spaces: dict[str, gym.Space], agent: str) -> gym.Space:
        """A learner's space of ``spaces``, or a ``ValueError`` for an agent that is no learner."""
        space = spaces.get(agent)
        if space is None:
            raise ValueError(
                f"{agent!r} is not an agent of this env: its agents are the learners "
                f"{_preview(self.possible_agents)}."
            )
        return space

    @property
    def neighbors(self) -> Callable[[], np.ndarray]:
        """``neighbors()``: the inner env's graph cut down to the learners, ``(n_learners,
        max_neighbors)`` int64 in ``possible_agents`` order (entries naming driven agents are ``-1``).

        Only where the inner env has ``neighbors()``: otherwise reading this attribute raises an
        ``AttributeError`` (wrap this env in :class:`GraphFromPositions` for a graph).
        """
        if not self._has_graph:
            raise AttributeError(
                f"{type(self.env).__name__} has no neighbors(), so DrivenAgents has no graph of the "
                "learners; wrap it in GraphFromPositions."
            )
        return self._learner_neighbors

    def _learner_neighbors(self) -> np.ndarray:
        return subgraph(
            _lists(self.env.neighbors(), len(self._inner_index), "the inner env's neighbors()"),
            self._learner_rows,
        )

    def state(self) -> np.ndarray:
        return self.env.state()

    def render(self) -> Any:
        return self.env.render()

    def close(self) -> None:
        self.env.close()

    @property
    def unwrapped(self) -> ParallelEnv:
        return self.env.unwrapped


class DrivenTeam(DrivenSide):
    """The agents a :class:`DrivenAgents` env drives, as its controller sees them (see there)."""

    def __init__(
        self,
        env: ParallelEnv,
        names: Sequence[str],
        rows: np.ndarray,
        controller_neighbors: Callable[[Any, list[str]], np.ndarray] | None,
    ) -> None:
        self.env = env
        self.names = tuple(names)
        self.action_spaces = tuple(env.action_space(name) for name in names)
        spaces = [env.observation_space(name) for name in names]
        shared = all(space == spaces[0] for space in spaces)
        self.observation_space = spaces[0] if shared else None
        if controller_neighbors is None and not callable(getattr(env, "neighbors", None)):
            self.no_graph_reason = (
                f"{type(env).__name__} has no neighbors(); pass controller_neighbors=(env, names) -> "
                "(n, K) int array, or give the inner env a graph (GraphFromPositions)."
            )
        self._rows = rows
        self._n_inner = len(env.possible_agents)
        self._controller_neighbors = controller_neighbors
        self._rng: np.random.Generator | None = None
        self._alive = np.zeros(len(self.names), dtype=bool)
        self._living = np.empty(0, dtype=np.int64)
        self.living_names: list[str] = []
        self._observed: dict[str, Any] = {}
        self._last_observations = (
            np.full(
                (len(self.names), *spaces[0].shape),
                np.clip(0, spaces[0].low, spaces[0].high),
                spaces[0].dtype,
            )
            if shared and isinstance(spaces[0], gym.spaces.Box)
            else None
        )

    def reseed(self, seed: int | None) -> None:
        """Reseed the generator with ``seed``; without one, seed it from entropy the first time only."""
        if seed is not None or self._rng is None:
            self._rng = np.random.default_rng(seed)

    def update(self, observations: dict, present: np.ndarray) -> None:
        """Take the inner env's observations and which of its agents are present ``(n_inner,)`` bool."""
        self._observed = observations
        self._alive = present[self._rows]
        self._living = np.flatnonzero(self._alive)
        self.living_names = [self.names[i] for i in self._living]

    @property
    def rng(self) -> np.random.Generator:
        return self._rng

    def living(self) -> np.ndarray:
        return self._living

    def observations(self) -> np.ndarray:
        if self._living.size:
            self._last_observations[self._living] = np.stack(
                [self._observed[name] for name in self.living_names]
            )
        return self._last_observations.copy()

    def named_observations(self) -> dict[str, Any]:
        return {name: self._observed[name] for name in self.living_names}

    def neighbors(self, width: int | None) -> np.ndarray:
        if self._controller_neighbors is None:
            inner = _lists(self.env.neighbors(), self._n_inner, "the inner env's neighbors()")
            lists = living_neighbors(subgraph(inner, self._rows), self._alive)
        else:
            living = self._living
            given = _lists(
                self._controller_neighbors(self.env, list(self.living_names)),
                len(living),
                "controller_neighbors",
            )
            lists = np.full((self.n_slots, given.shape[1]), -1, dtype=np.int32)
            lists[living] = np.where(given >= 0, living[given], -1)
        if width is None or width == lists.shape[1]:
            return lists.astype(np.int32, copy=False)
        if width < lists.shape[1]:
            raise ValueError(
                f"The neighbour lists of the driven agents are {lists.shape[1]} wide, wider than the "
                f"{width} the controller's model takes; give it lists at most {width} wide."
            )
        padded = np.full((self.n_slots, width), -1, dtype=np.int32)
        padded[:, : lists.shape[1]] = lists
        return padded


def _lists(graph: Any, n_rows: int, source: str) -> np.ndarray:
    """``graph`` as int64 neighbour lists of ``n_rows`` agents, or a ``ValueError`` naming ``source``
    when it is not a 2-D integer array of ``n_rows`` rows with entries in ``[-1, n_rows - 1]``."""
    lists = np.asarray(graph)
    if lists.ndim != 2 or lists.shape[0] != n_rows or lists.dtype.kind not in "iu":
        raise ValueError(
            f"{source} must return an integer array of shape ({n_rows}, K), got {lists.dtype} {lists.shape}."
        )
    if lists.size and (lists.min() < -1 or lists.max() >= n_rows):
        raise ValueError(
            f"{source} must return agent indices in [-1, {n_rows - 1}], got {lists.min()}..{lists.max()}."
        )
    return lists.astype(np.int64, copy=False)


def _learner_mask(agents: list[str], learners: Any) -> np.ndarray:
    """``(n_agents,)`` bool: which of ``agents`` the ``learners`` of :class:`DrivenAgents` select."""
    if isinstance(learners, str):
        mask = np.array([isinstance(agent, str) and agent.startswith(learners) for agent in agents])
        chosen = f"the prefix {learners!r}"
    elif callable(learners):
        mask = np.array([bool(learners(agent)) for agent in agents])
        chosen = "the predicate"
    elif isinstance(learners, Collection):
        names, known = set(learners), set(agents)
        unknown = [name for name in learners if name not in known]
        if unknown:
            raise ValueError(
                f"learners names {_preview(unknown)}, which the env does not have; its possible_agents "
                f"are {_preview(agents)}."
            )
        mask = np.array([agent in names for agent in agents])
        chosen = f"the names {_preview(list(learners))}"
    else:
        raise TypeError(
            "learners must be a collection of agent names, a name prefix (str) or a predicate "
            f"name -> bool, got {type(learners).__name__}."
        )
    if not mask.any():
        raise ValueError(f"learners ({chosen}) selects no agent of possible_agents {_preview(agents)}.")
    if mask.all():
        raise ValueError(
            f"learners ({chosen}) selects every agent, leaving none to drive; use the env itself."
        )
    return mask


def _preview(names: Sequence[Any]) -> str:
    """The first few ``names``, for error messages."""
    shown = ", ".join(repr(name) for name in names[:PREVIEW])
    return f"[{shown}{', ...' if len(names) > PREVIEW else ''}]"
