"""Flatten many-agent PettingZoo environments into one SB3 ``VecEnv`` of graph observations.

Slot layout: ``num_envs = n_copies * n_agents`` slots in copy-major order (copy 0 agents 0..N-1,
copy 1 agents 0..N-1, ...), so any per-slot array reshapes to ``(n_copies, n_agents, ...)``.
Each slot observes a dict with

* ``"obs"``: ``obs_shape`` the agent's local observation, a ``Box`` of any shape (``(obs_dim,)``,
  or e.g. ``(13, 13, 5)`` map views) in the env's own (compact) dtype and shape;
* ``"neighbors"``: ``(max_neighbors,)`` int32 indices of its neighbours within the same copy, the
  agent itself first, ``-1`` for unused entries (and all ``-1`` for an agent that died or left,
  see :class:`GraphVecEnv`);
* with several agent groups (heterogeneous envs) also ``"group"``: ``()`` int8 the agent's group id
  and ``"action_mask"``: ``(n_actions,)`` int8, 1 for the actions of its group. 1-D observations are
  then zero-padded to the widest group (observations of more dimensions must have one shape in all
  groups) and the action space is that of the group with most actions.

The neighbour space's bounds do not depend on the agent count, so a model trained with N agents
loads onto an env with M agents.
"""

from __future__ import annotations

import importlib
import pickle
import sys
from collections.abc import Callable, Sequence
from types import ModuleType
from typing import Any

import cloudpickle
import gymnasium as gym
import numpy as np
from pettingzoo import AECEnv, ParallelEnv
from stable_baselines3.common.vec_env import VecEnv
from stable_baselines3.common.vec_env.base_vec_env import VecEnvIndices, VecEnvObs, VecEnvStepReturn

from sb3_hgrn.common.checks import observation_problem, slot_name
from sb3_hgrn.common.safe_load import load_pickle
from sb3_hgrn.common.saved_controllers import resolve_model_paths
from sb3_hgrn.envs.base import GraphParallelEnv
from sb3_hgrn.envs.graph import living_neighbors
from sb3_hgrn.envs.wrappers import as_parallel_env
from sb3_hgrn.validation import is_integer

REGISTERED_ENVS = ("surviving_v0", "uav_mbs_v0", "pursuit_v0", "ctc_v0")
NEIGHBOR_INDEX_HIGH = np.iinfo(np.int32).max
# the keys of info["team_episode"] itself, which an env's team_info() must not take
TEAM_EPISODE_KEYS = frozenset({"r", "l", "agents", "final_observation", "terminated"})


class UnpicklableEnvError(TypeError):
    """An env copy whose state cannot be pickled (e.g. one driving a C library), so
    :meth:`GraphVecEnv.get_state` cannot save it."""


class ParallelEnvAdapter(GraphParallelEnv):
    """Array API over any PettingZoo ``ParallelEnv`` that supplies its graph.

    The wrapped env must give every agent the same spaces, have a ``max_neighbors`` attribute and a
    ``neighbors()`` method returning ``(n_agents, max_neighbors)`` agent indices in
    ``possible_agents`` order, the agent itself first (``-1`` = none).

    Agents may die or leave during an episode, as PettingZoo allows: an agent is alive while it is
    in the env's ``agents`` list (:attr:`alive`). Only living agents get actions; the arrays keep a
    row for every agent of ``possible_agents``, a gone agent's row holding its last observation, a
    reward of 0 and no done flags. Stepping an env without agents left raises a ``RuntimeError``
    before the env is called.

    An env with a ``team_info()`` method (such as :class:`~sb3_hgrn.envs.wrappers.TeamFigures`)
    gives the figures after each step that :class:`GraphVecEnv` adds to ``info["team_episode"]`` at
    an episode's end: a dict by name, whose names must differ from that dict's own keys.
    """

    def __init__(self, env: ParallelEnv):
        self.env = env
        self.possible_agents = list(env.possible_agents)
        self.shared_observation_space = env.observation_space(self.possible_agents[0])
        self.shared_action_space = env.action_space(self.possible_agents[0])
        for agent in self.possible_agents[1:]:
            if (
                env.observation_space(agent) != self.shared_observation_space
                or env.action_space(agent) != self.shared_action_space
            ):
                raise ValueError(
                    f"Agent {agent!r} has other observation or action spaces than "
                    f"{self.possible_agents[0]!r}; graph envs need one shared space for all agents."
                )
        if not callable(getattr(env, "neighbors", None)):
            raise TypeError(
                f"{type(env).__name__} supplies no communication graph: a ParallelEnv used with "
                "make_graph_vec_env must define neighbors() -> (n_agents, max_neighbors) int array. "
                "Wrap it in sb3_hgrn.GraphFromPositions(env, positions, k=...) to link agents by position."
            )
        self.max_neighbors = int(env.max_neighbors)
        team_info = getattr(env, "team_info", None)
        self._team_info = team_info if callable(team_info) else dict
        self.render_mode = getattr(env, "render_mode", None)
        space = self.shared_observation_space
        # the row of an agent not observed yet: the point of the space nearest to zero
        self._observations = np.full(
            (self.n_agents, *space.shape), np.clip(0, space.low, space.high), dtype=space.dtype
        )
        self._alive = np.zeros(self.n_agents, dtype=bool)

    @property
    def alive(self) -> np.ndarray:
        """``(n_agents,)`` bool: the agents in the env's ``agents`` list after the last reset or step."""
        return self._alive.copy()

    def reset_arrays(self, seed: int | None = None, options: dict | None = None) -> np.ndarray:
        observations, _ = self.env.reset(seed=seed, options=options)
        self._store_observations(observations)
        self._alive = self._listed(self.env.agents)
        return self._observations.copy()

    def step_arrays(self, actions: np.ndarray):
        agents = list(getattr(self.env, "agents", None) or ())
        if not agents:
            raise RuntimeError(
                f"{type(self.env).__name__} has no agents left: every agent has died or left, so its "
                "episode is over and it was not stepped; call reset() first."
            )
        rows = self._rows(agents)
        observations, rewards, terminations, truncations, _ = self.env.step(
            dict(zip(agents, actions[rows].tolist(), strict=True))
        )
        self._store_observations(observations)
        self._alive = self._listed(self.env.agents)
        n, possible = self.n_agents, self.possible_agents
        return (
            self._observations.copy(),
            np.fromiter((rewards.get(agent, 0.0) for agent in possible), dtype=np.float32, count=n),
            np.fromiter((terminations.get(agent, False) for agent in possible), dtype=bool, count=n),
            np.fromiter((truncations.get(agent, False) for agent in possible), dtype=bool, count=n),
            self._checked_team_info(),
        )

    def _checked_team_info(self) -> dict[str, Any]:
        """The env's ``team_info()``, or a ``TypeError`` / ``ValueError`` naming what is wrong with it."""
        team_info = self._team_info()
        if not isinstance(team_info, dict):
            raise TypeError(
                f"{type(self.env).__name__}.team_info() must return a dict, got {type(team_info).__name__}."
            )
        taken = sorted(TEAM_EPISODE_KEYS.intersection(team_info))
        if taken:
            raise ValueError(
                f"{type(self.env).__name__}.team_info() names {taken}, which info['team_episode'] holds "
                f"itself ({', '.join(sorted(TEAM_EPISODE_KEYS))}); rename them."
            )
        return team_info

    def _rows(self, agents: Sequence[str]) -> np.ndarray:
        """The ``possible_agents`` index of every agent in ``agents``, or a ``ValueError`` naming one
        that is not a possible agent."""
        index = self._agent_index
        unknown = [agent for agent in agents if agent not in index]
        if unknown:
            raise ValueError(
                f"{type(self.env).__name__} reports the agent {unknown[0]!r}, which is not in its "
                "possible_agents."
            )
        return np.fromiter((index[agent] for agent in agents), dtype=np.int64, count=len(agents))

    def _listed(self, agents: Sequence[str]) -> np.ndarray:
        """``(n_agents,)`` bool: which possible agents ``agents`` holds."""
        listed = np.zeros(self.n_agents, dtype=bool)
        listed[self._rows(agents)] = True
        return listed

    def _store_observations(self, observations: dict[str, np.ndarray]) -> None:
        """Write the observations the env returned into the rows of their agents (the others keep
        their last one)."""
        if observations:
            self._observations[self._rows(list(observations))] = np.stack(list(observations.values()))

    def neighbors(self) -> np.ndarray:
        return np.asarray(self.env.neighbors())

    def render(self):
        return self.env.render()

    def close(self) -> None:
        self.env.close()


def _check_groups(env: GraphParallelEnv) -> None:
    """Raise an error naming the problem unless ``env``'s agent groups fit its shared spaces."""
    if env.group_ids.shape != (env.n_agents,) or not set(env.group_ids.tolist()) <= set(
        range(len(env.groups))
    ):
        raise ValueError(
            f"group_ids must hold one group id in 0..{len(env.groups) - 1} per agent ({env.n_agents}), "
            f"got shape {env.group_ids.shape}."
        )
    shape = env.shared_observation_space.shape
    for group in env.groups:
        if not isinstance(group.action_space, gym.spaces.Discrete):
            raise TypeError(f"Graph envs need a Discrete action space, got {group.action_space}.")
        if group.action_space.n > env.shared_action_space.n:
            raise ValueError(
                f"Group {group.name!r} has {group.action_space.n} actions, more than the env's shared "
                f"spaces hold ({env.shared_action_space})."
            )
        group_shape = group.observation_space.shape
        if len(shape) == 1 and (len(group_shape) != 1 or group_shape[0] > shape[0]):
            raise ValueError(
                f"Group {group.name!r} observes shape {group_shape}, which does not fit the env's shared "
                f"1-D observation space of {shape[0]} values (groups are zero-padded to the widest)."
            )
        if len(shape) > 1 and group_shape != shape:
            raise ValueError(
                f"Group {group.name!r} observes shape {group_shape}, the env's shared observation space "
                f"{shape}: observations of more than one dimension are not padded, so every group must "
                "observe the shared shape (flatten them in the env to pad 1-D observations instead)."
            )


def as_graph_env(env: Any) -> GraphParallelEnv:
    """Return ``env`` with the array API, or raise a ``TypeError`` naming what is wrong with it.

    A parallelizable PettingZoo AEC env is converted to a ``ParallelEnv`` first (:func:`as_parallel_env`).
    """
    if isinstance(env, GraphParallelEnv):
        return env
    if isinstance(env, gym.Env):
        raise TypeError(
            f"Got the single-agent gymnasium env {type(env).__name__}; sb3_hgrn needs a many-agent "
            "PettingZoo ParallelEnv with a communication graph (use stable-baselines3 directly for "
            "single-agent envs)."
        )
    return ParallelEnvAdapter(as_parallel_env(env))


class GraphVecEnv(VecEnv):
    """SB3 ``VecEnv`` with one slot per agent of ``n_copies`` copies of a many-agent env.

    Copies are stepped in this process (one Python call per copy, none per agent). Every observation
    a copy returns (also the final one of an episode) is checked at once: a NaN or infinite value, one
    outside the observation space, or a neighbour index that is not a whole number in
    ``[-1, n_agents - 1]`` raises a ``ValueError`` naming the agent, its copy and the step.

    Agents may die or leave before their copy's episode ends (an agent whose env reports it
    terminated or truncated, or drops it from its ``agents`` list): a gone agent keeps its slot,
    and :attr:`alive` ``(num_envs,)`` says after every step and reset which slots hold a living
    agent. A gone agent sends and receives no messages (it is removed from every neighbour list and
    its own list is all ``-1``), earns a reward of 0 and counts in no team return; its slot keeps its
    last observation, and :attr:`terminations` ``(num_envs,)`` marks the step at which an agent's
    episode really ended (not time limits). A copy resets when none of its agents is left; its
    slots then report ``done=True``, the final observation in ``info["terminal_observation"]``,
    ``info["TimeLimit.truncated"]`` for time-limit ends and the team's episode figures in
    ``info["team_episode"]`` (see :meth:`_finish_episode`), and all its agents are alive again.

    :param env_fns: one callable per copy, each returning a PettingZoo ``ParallelEnv``.
    """

    def __init__(self, env_fns: Sequence[Callable[[], Any]]):
        if len(env_fns) == 0:
            raise ValueError("GraphVecEnv needs at least one env copy.")
        self.envs = [as_graph_env(fn()) for fn in env_fns]
        first = self.envs[0]
        self.n_agents = first.n_agents
        self.n_copies = len(self.envs)
        self.max_neighbors = first.max_neighbors
        for env in self.envs[1:]:
            if env.n_agents != self.n_agents:
                raise ValueError(
                    f"All env copies must have the same number of agents, got {env.n_agents} "
                    f"and {self.n_agents}."
                )
            if not np.array_equal(env.group_ids, first.group_ids):
                raise ValueError("All env copies must have the same agent groups.")
        if self.n_agents < 1:
            raise ValueError(f"A graph env needs at least one agent; {type(first).__name__} has none.")
        obs_space = first.shared_observation_space
        if not isinstance(obs_space, gym.spaces.Box) or len(obs_space.shape) == 0:
            raise TypeError(
                f"Agent observations must be a Box space of one or more dimensions, got {obs_space}."
            )
        self.groups = first.groups
        _check_groups(first)
        self.group_n_actions = tuple(int(group.action_space.n) for group in self.groups)
        spaces = {
            "obs": obs_space,
            "neighbors": gym.spaces.Box(-1, NEIGHBOR_INDEX_HIGH, shape=(self.max_neighbors,), dtype=np.int32),
        }
        self._group_keys: dict[str, np.ndarray] = {}
        if len(self.groups) > 1:
            n_actions = int(first.shared_action_space.n)
            group_ids = np.tile(first.group_ids, self.n_copies)
            masks = np.arange(n_actions) < np.array(self.group_n_actions)[:, None]
            spaces["group"] = gym.spaces.Box(0, len(self.groups) - 1, shape=(), dtype=np.int8)
            spaces["action_mask"] = gym.spaces.MultiBinary(n_actions)
            self._group_keys = {
                "group": group_ids.astype(np.int8),
                "action_mask": masks[group_ids].astype(np.int8),
            }
        super().__init__(self.n_copies * self.n_agents, gym.spaces.Dict(spaces), first.shared_action_space)
        self._seeds_per_copy: list[int | None] = [None] * self.n_copies
        self._actions = np.zeros(self.num_envs, dtype=np.int64)
        self._team_returns = np.zeros(self.n_copies, dtype=np.float64)
        self._episode_lengths = np.zeros(self.n_copies, dtype=np.int64)
        self._alive = np.ones((self.n_copies, self.n_agents), dtype=bool)
        self._took_part = np.ones((self.n_copies, self.n_agents), dtype=bool)
        self._terminations = np.zeros((self.n_copies, self.n_agents), dtype=bool)

    @property
    def alive(self) -> np.ndarray:
        """``(num_envs,)`` bool: the slots whose agent is alive in the last observations returned
        (by :meth:`reset` or :meth:`step`; all slots of a copy that was just reset)."""
        return self._alive.reshape(-1).copy()

    @property
    def terminations(self) -> np.ndarray:
        """``(num_envs,)`` bool: the slots whose agent's episode really ended (it died, or its copy's
        episode terminated) at the last :meth:`step`; time-limit ends and agents gone before are
        ``False``."""
        return self._terminations.reshape(-1).copy()

    # --- VecEnv API ----------------------------------------------------------------------------
    def reset(self) -> VecEnvObs:
        self._team_returns[:] = 0.0
        self._episode_lengths[:] = 0
        self._terminations[:] = False
        observations, neighbors = [], []
        for copy, (env, seed) in enumerate(zip(self.envs, self._seeds_per_copy, strict=True)):
            obs = env.reset_arrays(seed=seed, options=self._options[copy * self.n_agents] or None)
            obs, graph = self._started(copy, env, obs)
            observations.append(obs)
            neighbors.append(graph)
        self._seeds_per_copy = [None] * self.n_copies
        self._reset_seeds()
        self._reset_options()
        self.reset_infos = [{} for _ in range(self.num_envs)]
        return self._stack(observations, neighbors)

    def step_async(self, actions: np.ndarray) -> None:
        actions = np.asarray(actions).reshape(-1)
        if actions.shape[0] != self.num_envs:
            raise ValueError(f"Expected {self.num_envs} actions (one per slot), got {actions.shape[0]}.")
        self._actions = actions

    def step_wait(self) -> VecEnvStepReturn:
        n = self.n_agents
        observations, neighbors, rewards, dones = [], [], [], []
        infos: list[dict[str, Any]] = [{} for _ in range(self.num_envs)]
        for copy, env in enumerate(self.envs):
            acting = self._alive[copy].copy()
            obs, reward, terminated, truncated, team_info = env.step_arrays(
                self._actions[copy * n : (copy + 1) * n]
            )
            # agents gone before this step earn nothing and end nothing
            reward = np.where(acting, reward, np.float32(0.0))
            terminated, truncated = terminated & acting, truncated & acting
            self._terminations[copy] = terminated
            self._alive[copy] = acting & ~(terminated | truncated) & env.alive
            self._took_part[copy] |= acting
            self._team_returns[copy] += float(reward.sum())
            self._episode_lengths[copy] += 1
            ended = not self._alive[copy].any()
            # an episode cut short by a time limit ends with the graph of its last agents intact
            members = acting & ~terminated if ended else self._alive[copy]
            obs, graph = self._observed(copy, env, obs, members)
            if ended:
                self._finish_episode(copy, obs, graph, terminated, truncated, team_info, infos)
                obs, graph = self._started(copy, env, env.reset_arrays())
            observations.append(obs)
            neighbors.append(graph)
            rewards.append(reward)
            dones.append(np.full(n, ended))
        return (
            self._stack(observations, neighbors),
            np.concatenate(rewards).astype(np.float32, copy=False),
            np.concatenate(dones),
            infos,
        )

    def _finish_episode(self, copy, obs, graph, terminated, truncated, team_info, infos) -> None:
        """Fill the infos of every slot of ``copy`` at the end of its episode and zero its counters.

        Each slot gets SB3's ``terminal_observation`` and ``TimeLimit.truncated``; all slots share
        one ``team_episode`` dict with the team return ``r``, the length ``l``, the number of agents
        that were alive at some step of the episode ``agents``, the env's team figures, and the whole
        graph's ``final_observation`` and ``terminated`` arrays.
        """
        slots = slice(copy * self.n_agents, (copy + 1) * self.n_agents)
        final = {"obs": obs, "neighbors": graph}
        final.update({key: value[slots] for key, value in self._group_keys.items()})
        team_episode = {
            "r": float(self._team_returns[copy]),
            "l": int(self._episode_lengths[copy]),
            "agents": int(self._took_part[copy].sum()),
            **team_info,
            "final_observation": final,
            "terminated": terminated,
        }
        time_limit = (truncated & ~terminated).tolist()
        for agent in range(self.n_agents):
            infos[copy * self.n_agents + agent] = {
                "terminal_observation": {key: value[agent] for key, value in final.items()},
                "TimeLimit.truncated": time_limit[agent],
                "team_episode": team_episode,
            }
        self._team_returns[copy] = 0.0
        self._episode_lengths[copy] = 0

    def _started(self, copy: int, env: GraphParallelEnv, obs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`_observed` for the first observations of an episode, which must have a living agent."""
        self._alive[copy] = env.alive
        self._took_part[copy] = self._alive[copy]
        if not self._alive[copy].any():
            raise ValueError(f"Env copy {copy} ({type(env).__name__}) has no agents after its reset.")
        return self._observed(copy, env, obs, self._alive[copy])

    def _observed(
        self, copy: int, env: GraphParallelEnv, obs: np.ndarray, members: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """One copy's checked observations and the neighbour lists of its graph's ``members``
        ``(n_agents,)`` bool (see :func:`~sb3_hgrn.envs.graph.living_neighbors`); without members the
        env's graph is not asked for."""
        if not members.any():
            graph = np.full((self.n_agents, self.max_neighbors), -1, dtype=np.int32)
            return self._checked(copy, obs, graph)
        obs, graph = self._checked(copy, obs, env.neighbors())
        return obs, graph if members.all() else living_neighbors(graph, members)

    def _checked(self, copy: int, obs: np.ndarray, graph: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One copy's observations ``(n_agents, *obs_shape)`` and neighbours ``(n_agents, max_neighbors)``
        as returned by its env, after checking them (see the class docstring); the neighbours come
        back as int32."""
        expected = (self.n_agents, self.max_neighbors)
        if graph.shape != expected:
            raise ValueError(f"neighbors() must return shape {expected} (max_neighbors), got {graph.shape}.")
        problem = observation_problem(
            {"obs": obs, "neighbors": graph}, self.observation_space["obs"], self.n_agents
        )
        if problem is not None:
            agent, what = problem
            raise ValueError(
                f"The env returned {what} for {slot_name(copy * self.n_agents + agent, self.n_agents)} at "
                f"step {self._episode_lengths[copy]} of the copy's episode (0: its reset)."
            )
        return obs, graph.astype(np.int32)

    def _stack(self, observations: list[np.ndarray], neighbors: list[np.ndarray]) -> dict[str, np.ndarray]:
        stacked = {"obs": np.concatenate(observations), "neighbors": np.concatenate(neighbors)}
        stacked.update({key: value.copy() for key, value in self._group_keys.items()})
        return stacked

    def seed(self, seed: int | None = None) -> Sequence[None | int]:
        """Seed copy ``c`` with ``seed + c`` at the next ``reset()``; returns the per-slot seeds."""
        if seed is None:
            seed = int(np.random.randint(0, np.iinfo(np.uint32).max - self.n_copies))
        self._seeds_per_copy = [seed + copy for copy in range(self.n_copies)]
        return [seed + slot // self.n_agents for slot in range(self.num_envs)]

    def close(self) -> None:
        for env in self.envs:
            env.close()

    # --- state of the copies, for an exact resume ------------------------------------------------
    def get_state(self) -> bytes:
        """The state of every copy and of this VecEnv's own counters, as a pickle (cloudpickle).

        The copies are pickled whole (their random generators, positions, step counters, ...), with
        the running team returns and episode lengths, which agents are alive, and the seeds and
        options of the next :meth:`reset`; :meth:`set_state` on a VecEnv of the same env makes it
        step on exactly as this one would. Raises :class:`UnpicklableEnvError` naming the env when a
        copy cannot be pickled.
        """
        state = {
            "n_copies": self.n_copies,
            "n_agents": self.n_agents,
            "envs": self.envs,
            "team_returns": self._team_returns,
            "episode_lengths": self._episode_lengths,
            "alive": self._alive,
            "took_part": self._took_part,
            "terminations": self._terminations,
            "seeds_per_copy": self._seeds_per_copy,
            "options": self._options,
        }
        try:
            return cloudpickle.dumps(state)
        except (pickle.PicklingError, TypeError, ValueError, AttributeError) as error:
            raise UnpicklableEnvError(
                f"The state of {type(self.envs[0]).__name__} cannot be pickled: {error}"
            ) from error

    def set_state(self, state: bytes, trust_pickle: bool = False) -> None:
        """Replace the copies and counters by those of :meth:`get_state` (the current copies are
        closed); a state of another copy or agent count raises a ``ValueError`` saying so.

        The state is read by :func:`~sb3_hgrn.common.safe_load.restricted_loads`, which builds only
        numpy arrays and generators, gymnasium spaces and the classes of the modules that define
        this VecEnv's copies (and the envs they wrap); a state that needs more (an env pickled by
        value, e.g. one defined in ``__main__``) raises
        :class:`~sb3_hgrn.common.safe_load.UntrustedPickleError` naming it. ``trust_pickle=True``
        unpickles it in full, which can run code: only for states you trust.
        """
        source = f"the state of {type(self.envs[0]).__name__}"
        loaded = load_pickle(state, source, trust_pickle, self._env_classes())
        saved, own = (loaded["n_copies"], loaded["n_agents"]), (self.n_copies, self.n_agents)
        if saved != own:
            raise ValueError(
                f"The env state holds {saved[0]} copies of {saved[1]} agents, this VecEnv {own[0]} "
                f"of {own[1]}."
            )
        self.close()
        self.envs = loaded["envs"]
        self._team_returns = loaded["team_returns"]
        self._episode_lengths = loaded["episode_lengths"]
        # states of VecEnvs whose agents could not die have every agent alive
        self._alive = loaded.get("alive", np.ones((self.n_copies, self.n_agents), dtype=bool))
        self._took_part = loaded.get("took_part", np.ones((self.n_copies, self.n_agents), dtype=bool))
        self._terminations = loaded.get("terminations", np.zeros((self.n_copies, self.n_agents), dtype=bool))
        self._seeds_per_copy = loaded["seeds_per_copy"]
        self._options = loaded["options"]

    def _env_classes(self) -> list[type]:
        """The classes defined in the modules of this VecEnv's copies, of the envs they wrap (through
        ``.env``) and of their base classes, ``sb3_hgrn.envs.base`` among them: what an env state
        may build."""
        modules, seen = {"sb3_hgrn.envs.base"}, set()
        for env in self.envs:
            while env is not None and id(env) not in seen:
                seen.add(id(env))
                modules.update(cls.__module__ for cls in type(env).__mro__)
                env = getattr(env, "env", None)
        modules -= {"builtins", "abc", "typing"}
        return [
            value
            for module in modules
            if module in sys.modules
            for value in vars(sys.modules[module]).values()
            if isinstance(value, type) and value.__module__ == module
        ]

    def render(self, mode: str | None = None) -> np.ndarray | None:
        """Render copy 0 (its ``render_mode`` is set through ``env_kwargs``)."""
        return self.envs[0].render()

    def get_images(self) -> Sequence[np.ndarray | None]:
        return [env.render() for env in self.envs]

    # --- attribute access: slot indices map to their copy --------------------------------------
    def _copies(self, indices: VecEnvIndices) -> list[GraphParallelEnv]:
        return [self.envs[slot // self.n_agents] for slot in self._get_indices(indices)]

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        return [getattr(env, attr_name) for env in self._copies(indices)]

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        for env in self._copies(indices):
            setattr(env, attr_name, value)

    def env_method(self, method_name: str, *method_args, indices: VecEnvIndices = None, **method_kwargs):
        return [getattr(env, method_name)(*method_args, **method_kwargs) for env in self._copies(indices)]

    def env_is_wrapped(self, wrapper_class: type[gym.Wrapper], indices: VecEnvIndices = None) -> list[bool]:
        return [False for _ in self._get_indices(indices)]


def _resolve_env_fn(
    env: str | ModuleType | ParallelEnv | AECEnv | Callable[..., Any], n_envs: int, has_kwargs: bool
) -> Callable[..., Any]:
    """The constructor of one env copy named by ``env`` (see :func:`make_graph_vec_env`)."""
    if isinstance(env, str):
        if env not in REGISTERED_ENVS:
            raise ValueError(f"Unknown env {env!r}; registered envs: {', '.join(REGISTERED_ENVS)}.")
        return importlib.import_module(f"sb3_hgrn.envs.{env}").parallel_env
    if isinstance(env, ModuleType):
        if not callable(getattr(env, "parallel_env", None)):
            raise TypeError(
                f"Module {env.__name__} has no parallel_env(); pass a callable returning a ParallelEnv."
            )
        return env.parallel_env
    if isinstance(env, ParallelEnv | AECEnv):
        if n_envs != 1 or has_kwargs:
            raise ValueError(
                f"An env instance ({type(env).__name__}) makes one copy and takes no env_kwargs; for "
                f"n_envs={n_envs} or env_kwargs pass a callable that builds a new env at each call, "
                "e.g. lambda **kwargs: GraphFromPositions(MyEnv(**kwargs), positions, k=4)."
            )
        return lambda: env
    if callable(env):
        return env
    raise TypeError(
        "env must be a registered env name, a callable returning a PettingZoo ParallelEnv, an env "
        f"module with parallel_env(), or (for n_envs=1) a ParallelEnv or AEC env; got {type(env).__name__}."
    )


def make_graph_vec_env(
    env: str | ModuleType | ParallelEnv | AECEnv | Callable[..., Any],
    n_envs: int = 1,
    seed: int | None = None,
    env_kwargs: dict[str, Any] | None = None,
) -> GraphVecEnv:
    """Create a :class:`GraphVecEnv` of ``n_envs`` copies of a many-agent env.

    :param env: a registered env name (``"surviving_v0"``), a callable returning a PettingZoo
        ``ParallelEnv`` (called with ``**env_kwargs``), a module with such a ``parallel_env``
        (PettingZoo's env modules), or, for ``n_envs=1`` without ``env_kwargs``, an env instance.
        A PettingZoo AEC env is accepted wherever a ``ParallelEnv`` is if its metadata declares
        ``is_parallelizable``. The env must supply a graph (``neighbors()`` and ``max_neighbors``);
        :class:`sb3_hgrn.GraphFromPositions` adds one built from agent positions.
    :param n_envs: number of env copies; the VecEnv has ``n_envs * n_agents`` slots.
    :param seed: copy ``c`` is seeded with ``seed + c`` at the first reset.
    :param env_kwargs: keyword arguments for the env constructor. The saved models' paths among them
        that the env's module names with ``model_paths`` (Pursuit's ``prey_controller="runs/prey.zip"``)
        are loaded here, once, as controllers shared by the copies (see
        :func:`~sb3_hgrn.common.saved_controllers.resolve_model_paths`).
    """
    if not is_integer(n_envs) or n_envs < 1:
        raise ValueError(f"n_envs must be a positive integer (env copies), got {n_envs!r}.")
    env_fn = _resolve_env_fn(env, n_envs, bool(env_kwargs))
    kwargs = resolve_model_paths(env_fn, dict(env_kwargs or {}))
    vec_env = GraphVecEnv([lambda: env_fn(**kwargs) for _ in range(n_envs)])
    if seed is not None:
        vec_env.seed(seed)
    return vec_env
