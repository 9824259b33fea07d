"""Driven sides and their controllers: what chooses the actions of the agents an env drives instead
of learning.

An env whose learners play against (or beside) agents that do not learn, such as Pursuit's other side
or the other team of :class:`~sb3_hgrn.envs.wrappers.DrivenAgents`, describes those agents as a
:class:`DrivenSide` and asks a :class:`Controller` for their actions at every step.
:func:`make_controller` builds the controller from what the user passed:

- ``"random"``: uniform actions from each driven agent's ``Discrete`` action space
  (:class:`RandomController`);
- a function ``(observations: dict[name, obs], env) -> dict[name, action]`` (:class:`FunctionController`);
- a model with SB3's ``predict`` (:class:`ModelDriver`), e.g. an sb3_hgrn model wrapped in
  ``sb3_hgrn.common.saved_controllers.ModelController``;
- a name the env adds for a scripted controller of its own (Pursuit's ``"evader"``).

The env side loads no saved model: a path is refused here, and loaded on the learner side
(``ModelController(path)``, or :func:`sb3_hgrn.make_graph_vec_env` for the arguments that the env's
module names with ``model_paths``, see :func:`controller_paths`).
"""

from __future__ import annotations

import abc
import os
from collections.abc import Callable, Collection, Mapping, Sequence
from typing import Any

import gymnasium as gym
import numpy as np

RANDOM = "random"
SEED_HIGH = 2**31 - 1  # the seeds handed to a model's seed(): C ints


class DrivenSide(abc.ABC):
    """The agents an env drives, as its controller sees them.

    Every driven agent has a fixed slot ``0..n_slots - 1`` for the whole episode (the order of
    :attr:`names`); :meth:`living` says which are still in the episode. The attributes describe the
    side; the methods read the current step.

    Attributes:
        env: the env the driven agents live in (what a function controller gets as its second argument).
        names: the driven agents' names, in slot order.
        action_spaces: each slot's action space.
        observation_space: the observation space the slots share, ``None`` where they differ.
        no_graph_reason: why :meth:`neighbors` has no graph to give, ``None`` where it has one.
    """

    env: Any
    names: tuple[str, ...]
    action_spaces: tuple[gym.Space, ...]
    observation_space: gym.Space | None
    no_graph_reason: str | None = None

    @property
    def n_slots(self) -> int:
        return len(self.names)

    @property
    @abc.abstractmethod
    def rng(self) -> np.random.Generator:
        """The env's generator, which seeds the controller (reseeded by the env's seeded resets)."""

    @abc.abstractmethod
    def living(self) -> np.ndarray:
        """``(n_living,)`` int64: the slots of the driven agents still in the episode, ascending."""

    @abc.abstractmethod
    def observations(self) -> np.ndarray:
        """``(n_slots, *obs_shape)``: every slot's observation; a gone agent's slot keeps the last one
        read here while it lived."""

    @abc.abstractmethod
    def named_observations(self) -> dict[str, Any]:
        """The living driven agents' observations by name, in slot order."""

    @abc.abstractmethod
    def neighbors(self, width: int | None) -> np.ndarray:
        """``(n_slots, width)`` int32 neighbour lists among the slots (``width=None``: the side's own
        width): row ``i`` is slot ``i`` itself, then its neighbours, ``-1`` pads; a gone agent's row is
        all ``-1`` and no row lists it."""


class Controller(abc.ABC):
    """Chooses the actions of the agents of a :class:`DrivenSide` at every step."""

    def reset(self) -> None:  # noqa: B027 (most controllers keep nothing between episodes)
        """Forget the last episode (called at every episode start)."""

    @abc.abstractmethod
    def actions(self, side: DrivenSide) -> Sequence[Any]:
        """The actions of the living driven agents (``side.living()``), in that order."""


class RandomController(Controller):
    """Uniform actions from every driven agent's ``Discrete`` action space, drawn from the env's
    generator (so a seeded episode repeats).

    :raises TypeError: naming a driven agent whose action space is not ``Discrete``.
    """

    def __init__(self, side: DrivenSide, argument: str = "controller") -> None:
        for name, space in zip(side.names, side.action_spaces, strict=True):
            if not isinstance(space, gym.spaces.Discrete):
                raise TypeError(
                    f"{argument}={RANDOM!r} draws from Discrete action spaces, but {name!r} has {space}; "
                    "pass a function (observations, env) -> actions for it instead."
                )
        low = np.array([space.start for space in side.action_spaces], dtype=np.int64)
        high = low + np.array([space.n for space in side.action_spaces], dtype=np.int64)
        # one bound for all slots where they share it: the draw is then one scalar-bounded call
        self._shared = bool((low == low[0]).all() and (high == high[0]).all())
        self._low, self._high = (int(low[0]), int(high[0])) if self._shared else (low, high)

    def actions(self, side: DrivenSide) -> np.ndarray:
        """``(n_living,)`` int32 actions."""
        living = side.living()
        low, high = (self._low, self._high) if self._shared else (self._low[living], self._high[living])
        return side.rng.integers(low, high, size=len(living), dtype=np.int32)


class FunctionController(Controller):
    """A scripted controller: ``function(observations, env) -> actions``, with ``observations`` the
    living driven agents' observations by name and ``actions`` one action per name of them.

    :raises ValueError: at a step where the function leaves out a living driven agent or names an
        agent it does not drive.
    """

    def __init__(self, function: Callable[[dict[str, Any], Any], Mapping[str, Any]]) -> None:
        self.function = function

    def actions(self, side: DrivenSide) -> list[Any]:
        observations = side.named_observations()
        actions = self.function(observations, side.env)
        if not isinstance(actions, Mapping):
            raise TypeError(
                f"The controller function {self._name} must return a dict of actions by agent name, got "
                f"{type(actions).__name__}."
            )
        if len(actions) != len(observations) or any(name not in actions for name in observations):
            missing = [name for name in observations if name not in actions]
            extra = [name for name in actions if name not in observations]
            raise ValueError(
                f"The controller function {self._name} must return an action for each agent it is given "
                f"observations of, and only those: missing {missing}, not driven or gone {extra}."
            )
        return [actions[name] for name in observations]

    @property
    def _name(self) -> str:
        return getattr(self.function, "__qualname__", type(self.function).__name__)


class ModelDriver(Controller):
    """A model with SB3's ``predict`` driving every slot of a side as one graph.

    At every step the model gets ``{"obs": (n_slots, *obs_shape), "neighbors": (n_slots, K) int32}``
    for all slots (a gone agent keeps its slot, with the last observation the model had of it and an
    all ``-1`` list, and no list names it; its action is dropped) and returns ``(actions (n_slots,),
    state)``. Its recurrent ``state`` is carried through the episode and reset by :meth:`reset`. ``K``
    is the width of the model's ``observation_space["neighbors"]`` where it has a Dict observation
    space, else the side's. Two methods of the model are optional: ``bind(observation_space,
    n_agents)``, called here once with the side's shared observation space and slot count, and
    ``seed(seed)``, called with an int from the env's generator before every ``predict``, so that a
    sampling model repeats with the env's seed.

    :raises ValueError: when the slots do not share one ``Box`` observation space or the side has
        no graph.
    """

    def __init__(
        self, model: Any, side: DrivenSide, deterministic: bool = False, argument: str = "controller"
    ):
        if not isinstance(side.observation_space, gym.spaces.Box):
            raise ValueError(
                f"{argument} is a model, which observes all the agents it drives as one batch, but they "
                f"do not share one Box observation space (got {side.observation_space})."
            )
        if side.no_graph_reason is not None:
            raise ValueError(
                f"{argument} is a model, which needs the neighbour lists of the agents it drives: "
                f"{side.no_graph_reason}"
            )
        self.model = model
        self.deterministic = deterministic
        bind = getattr(model, "bind", None)
        if callable(bind):
            bind(side.observation_space, side.n_slots)
        space = getattr(model, "observation_space", None)
        self.width = (
            int(space["neighbors"].shape[0])
            if isinstance(space, gym.spaces.Dict) and "neighbors" in space.spaces
            else None
        )
        self._state: Any = None
        self._episode_start = np.ones(side.n_slots, dtype=bool)

    def reset(self) -> None:
        self._state = None
        self._episode_start[:] = True

    def actions(self, side: DrivenSide) -> np.ndarray:
        """``(n_living,)`` actions of the living slots."""
        observation = {"obs": side.observations(), "neighbors": side.neighbors(self.width)}
        # a seed per step from the env's generator makes a sampling model repeat with the episode
        seed = int(side.rng.integers(SEED_HIGH))
        if callable(getattr(self.model, "seed", None)):
            self.model.seed(seed)
        actions, self._state = self.model.predict(
            observation,
            state=self._state,
            episode_start=self._episode_start,
            deterministic=self.deterministic,
        )
        self._episode_start[:] = False
        return np.asarray(actions).reshape(side.n_slots)[side.living()]


def is_model(spec: Any) -> bool:
    """Whether ``spec`` is a model controller: an object with SB3's ``predict``."""
    return callable(getattr(spec, "predict", None))


def make_controller(
    spec: Any,
    side: DrivenSide,
    argument: str = "controller",
    deterministic: bool = False,
    scripted: Mapping[str, Callable[[], Controller]] | None = None,
) -> Controller:
    """The :class:`Controller` that ``spec`` names for the agents of ``side``.

    :param spec: ``"random"``, a name of ``scripted``, a model with ``predict`` or a function
        ``(observations, env) -> actions`` (see the module docstring).
    :param side: the driven agents.
    :param argument: the env argument that gave ``spec``, for error messages.
    :param deterministic: greedy actions for a model.
    :param scripted: the env's own scripted controllers by name, each built by calling it.
    :raises ValueError: for another string, or a path (the env side loads no saved model).
    :raises TypeError: for anything else that is no controller.
    """
    scripted = dict(scripted or {})
    names = (RANDOM, *scripted)
    if isinstance(spec, str) and spec in names:
        return RandomController(side, argument) if spec == RANDOM else scripted[spec]()
    if isinstance(spec, str | os.PathLike):
        raise ValueError(
            f"{argument} must be one of {names}, a function or a model with predict(); {spec!r} is neither. "
            "The env loads no saved model: pass it loaded (sb3_hgrn.common.saved_controllers.ModelController"
            "(path)), or build the env with sb3_hgrn.make_graph_vec_env or the command line, which load "
            "a saved model's path given in env_kwargs (for an env of your own, the arguments its module's "
            "model_paths names)."
        )
    if is_model(spec):
        return ModelDriver(spec, side, deterministic, argument)
    if callable(spec):
        return FunctionController(spec)
    raise TypeError(
        f"{argument} must be one of {names}, a function (observations, env) -> actions, an object with "
        f"predict() or (through make_graph_vec_env) a saved model's path, got {type(spec).__name__}."
    )


def controller_paths(
    env_kwargs: Mapping[str, Any], arguments: Mapping[str, Collection[str]]
) -> dict[str, str]:
    """The controllers of ``env_kwargs`` given as saved models' paths, by argument name.

    An env module's ``model_paths(env_kwargs)`` returns this, so that
    :func:`sb3_hgrn.make_graph_vec_env` and the command line load those models (as
    ``ModelController``) before they build the env::

        def model_paths(env_kwargs):
            return controller_paths(env_kwargs, {"controller": ("random",)})

    :param env_kwargs: the env's keyword arguments.
    :param arguments: the controller arguments, each with the names it takes that are no path.
    :return: ``{argument: path}`` for every argument of ``arguments`` set to a string or path-like
        other than its names.
    """
    paths = {}
    for argument, names in arguments.items():
        spec = env_kwargs.get(argument)
        if isinstance(spec, str | os.PathLike) and spec not in names:
            paths[argument] = os.fspath(spec)
    return paths
