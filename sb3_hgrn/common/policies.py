"""Policy base for graph observations: slot batches <-> graphs, and recurrent ``predict``."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, ClassVar

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import Schedule
from torch import nn

from sb3_hgrn.common.arguments import argument_hints, check_argument_types, named_parameters
from sb3_hgrn.common.attention import GraphBatch
from sb3_hgrn.common.averaging import polyak_average
from sb3_hgrn.common.checks import check_graph_batch, check_state, observation_problem, slot_name
from sb3_hgrn.common.hgrn import HGRN
from sb3_hgrn.common.optimizers import fused_by_default
from sb3_hgrn.common.temperature import EntropyTemperature
from sb3_hgrn.validation import is_number

GraphObs = dict[str, th.Tensor]
NO_AGENT_COUNT = "The policy does not know n_agents yet; attach a graph env to the model."


def check_graph_spaces(observation_space: spaces.Space, action_space: spaces.Space) -> None:
    """Raise a clear error unless the spaces are those of a graph VecEnv with discrete actions."""
    if not (
        isinstance(observation_space, spaces.Dict) and {"obs", "neighbors"} <= set(observation_space.spaces)
    ):
        raise TypeError(
            "Graph policies need the Dict observation space of a graph VecEnv (keys 'obs' and "
            f"'neighbors'; build the env with sb3_hgrn.make_graph_vec_env), got {observation_space}."
        )
    if not isinstance(action_space, spaces.Discrete):
        raise TypeError(f"Graph policies need a Discrete action space, got {action_space}.")
    if ("group" in observation_space.spaces) != ("action_mask" in observation_space.spaces):
        raise TypeError("A graph observation space with agent groups needs both 'group' and 'action_mask'.")


NETWORK_OPTIONS = (
    "hidden_dim", "n_heads", "head_dim", "communication", "recurrent", "mixed_precision",
    "features_extractor_class", "features_extractor_kwargs", "compile_network",
)  # fmt: skip
"""The arguments of :class:`GraphPolicy` that shape its networks (:meth:`GraphPolicy.make_network`)."""
SPACE_ARGUMENTS = ("observation_space", "action_space", "lr_schedule")
"""The arguments of a policy that the algorithm gives, never ``policy_kwargs``."""


def policy_parameters(policy_class: type[GraphPolicy]) -> list[str]:
    """The arguments a graph policy class takes in ``policy_kwargs``: its own and those of its bases
    down to :class:`GraphPolicy`."""
    bases = policy_class.__mro__[: policy_class.__mro__.index(GraphPolicy) + 1]
    names = [name for cls in bases for name in named_parameters(cls.__init__)]
    return [name for name in dict.fromkeys(names) if name not in SPACE_ARGUMENTS]


def check_policy_kwargs(
    policy_class: type[GraphPolicy],
    policy_kwargs: dict[str, Any],
    algorithm: Callable[..., Any],
    name: str = "policy_kwargs",
) -> None:
    """Raise a ``TypeError`` naming the argument unless every entry of ``policy_kwargs`` is an argument
    of ``policy_class`` with a value of its annotated type (for numbers and flags, see
    :mod:`sb3_hgrn.common.arguments`), and every entry of its :attr:`GraphPolicy.network_arguments`
    a network option of such a value.

    :param algorithm: the algorithm's constructor, to say when a misplaced key is its argument.
    :param name: what the messages call ``policy_kwargs`` (``default.policy_kwargs`` in a config file).
    """
    accepted = policy_parameters(policy_class)
    for key in policy_kwargs:
        if key not in accepted:
            hint = (
                f"; {key} is an argument of {algorithm.__qualname__.split('.')[0]} itself"
                if key in named_parameters(algorithm)
                else ""
            )
            raise TypeError(
                f"{name}.{key} is not an argument of {policy_class.__name__}; its arguments: "
                f"{', '.join(accepted)}{hint}."
            )
    bases = policy_class.__mro__[: policy_class.__mro__.index(GraphPolicy) + 1]
    hints = {name: kinds for cls in reversed(bases) for name, kinds in argument_hints(cls.__init__).items()}
    check_argument_types(hints, policy_kwargs, f"{name}.")
    for network in policy_class.network_arguments:
        options = policy_kwargs.get(network) or {}
        for key in options:
            if key not in NETWORK_OPTIONS:
                raise TypeError(
                    f"{name}.{network}.{key} is not a network option; the network options: "
                    f"{', '.join(NETWORK_OPTIONS)}."
                )
        check_argument_types(hints, options, f"{name}.{network}.")


class GraphPolicy(BasePolicy):
    """Base of the graph policies: every ``n_agents`` consecutive slots form one graph.

    Subclasses build their HGRN networks with :meth:`make_network`, list those whose recurrent
    state is carried between steps in :attr:`recurrent_networks` (the carried state is their states
    concatenated in that order), name the network that acts in :attr:`acting_network_name`, call
    :meth:`keep_average` once it is built, and implement :meth:`act_with`. ``n_agents`` is not a saved
    hyperparameter: the algorithm sets it from the env it runs on, so the same weights serve any
    agent count.

    :param observation_space: Dict space with ``obs`` (a ``Box`` of any shape ``obs_shape``) and
        ``neighbors`` ``(K,)`` (and ``group``, ``action_mask`` with agent groups).
    :param action_space: Discrete action space.
    :param lr_schedule: learning-rate schedule of the optimiser.
    :param hidden_dim: width H of the encoder, the attention layers and the recurrent state.
    :param n_heads: attention heads.
    :param head_dim: width of one head (``None``: ``hidden_dim // n_heads``).
    :param communication: ``"hgat"`` (graph attention), ``"mean"`` (CommNet mean) or ``"none"``.
    :param recurrent: use the GRU memory.
    :param mixed_precision: bfloat16 matrix products in the networks (see :class:`HGRN`).
    :param compile_network: run the networks' encoders and communication under ``torch.compile``
        (``True``, or a dict of its keyword arguments; see :class:`HGRN`).
    :param stochastic: sample actions from the policy; ``False`` acts greedily (the ``-S`` variants).
    :param alpha_log_space: learn ``log(alpha)`` instead of the temperature alpha itself.
    :param group_n_actions: action count of every agent group (set by the algorithm from a
        heterogeneous env; ``None``: one group). Every group has its own network parameters and alpha.
    :param features_extractor_class: SB3-style features extractor, built as
        ``features_extractor_class(observation_space["obs"], **features_extractor_kwargs)`` once per
        network and agent group, mapping observations ``(batch, *obs_shape)`` (float32, values as the
        env gives them) to ``(batch, features_dim)``; its features take the observation's place at
        the input of every HGRN (see :class:`~sb3_hgrn.common.hgrn.HGRN`). ``None``: the flattened
        observation.
    :param features_extractor_kwargs: keyword arguments of ``features_extractor_class``.
    :param optimizer_class: optimiser of the networks (SB3's option).
    :param optimizer_kwargs: its keyword arguments; for ``Adam`` and ``AdamW`` they default to
        ``fused=True`` unless they name ``fused`` or ``foreach``
        (:func:`~sb3_hgrn.common.optimizers.fused_by_default`).
    :param average_tau: keep a Polyak average of the acting network's weights (the Q-network, or the
        actor), updated after every gradient step (:meth:`update_average`; about the last tenth of
        the updates, at most the last ``1 / average_tau``: see
        :class:`~sb3_hgrn.common.averaging.PolyakWeight`), and let :meth:`act`, hence ``predict``
        and every evaluation, act with it. Collecting experience and the learning targets keep
        using the online networks. ``None``: act with the online network.
    """

    acting_network_name: ClassVar[str]
    """Attribute name of the network that chooses the actions (its average is ``<name>_average``)."""

    acting_network_label: ClassVar[str] = "network"
    """What the network that chooses the actions is, in words (reports of what is deployed)."""

    network_arguments: tuple[str, ...] = ()
    """Arguments of a subclass that hold :data:`NETWORK_OPTIONS` overriding the policy's for some of its
    networks (checked by :func:`check_policy_kwargs`)."""

    def __init__(
        self,
        observation_space: spaces.Dict,
        action_space: spaces.Discrete,
        lr_schedule: Schedule,
        hidden_dim: int = 64,
        n_heads: int = 4,
        head_dim: int | None = None,
        communication: str = "hgat",
        recurrent: bool = True,
        mixed_precision: bool = False,
        stochastic: bool = True,
        alpha_log_space: bool = False,
        group_n_actions: list[int] | None = None,
        features_extractor_class: type[nn.Module] | None = None,
        features_extractor_kwargs: dict[str, Any] | None = None,
        optimizer_class: type[th.optim.Optimizer] = th.optim.Adam,
        optimizer_kwargs: dict[str, Any] | None = None,
        normalize_images: bool = False,
        average_tau: float | None = 0.002,
        compile_network: bool | dict = False,
    ):
        check_graph_spaces(observation_space, action_space)
        super().__init__(
            observation_space,
            action_space,
            optimizer_class=optimizer_class,
            optimizer_kwargs=fused_by_default(optimizer_class, optimizer_kwargs),
            normalize_images=False,
        )
        if average_tau is not None and not (is_number(average_tau) and 0 < average_tau <= 1):
            raise ValueError(f"average_tau must be a number in (0, 1] or None, got {average_tau!r}.")
        self.average_tau = average_tau
        arguments = locals()
        self.network_kwargs = {name: arguments[name] for name in NETWORK_OPTIONS}
        if ("group" in observation_space.spaces) != (group_n_actions is not None):
            raise ValueError(
                "group_n_actions must be given exactly when the observations carry agent groups; build "
                "the model from the heterogeneous graph VecEnv."
            )
        self.group_n_actions = None if group_n_actions is None else [int(n) for n in group_n_actions]
        self.n_groups = 1 if group_n_actions is None else len(group_n_actions)
        self.lr_schedule = lr_schedule
        self.stochastic = stochastic
        self.alpha_log_space = alpha_log_space
        self.temperature = EntropyTemperature(log_space=alpha_log_space, n_groups=self.n_groups)
        self.n_agents: int | None = None

    @property
    def action_counts(self) -> list[int]:
        """Action count of every agent group."""
        return self.group_n_actions or [int(self.action_space.n)]

    def make_network(self, **overrides: Any) -> HGRN:
        """A fresh HGRN mapping each agent's observation to one value per action.

        :param overrides: network options replacing the policy's (e.g. ``communication="none"``).
        """
        options = {**self.network_kwargs, **overrides}
        extractor_class = options.pop("features_extractor_class", None)
        extractor_kwargs = dict(options.pop("features_extractor_kwargs", None) or {})
        obs_space = self.observation_space["obs"]
        if extractor_class is not None and not callable(extractor_class):
            raise TypeError(
                f"features_extractor_class must be a class such as a subclass of SB3's "
                f"BaseFeaturesExtractor, got {extractor_class!r}."
            )
        return HGRN(
            obs_dim=obs_space.shape,
            n_actions=int(self.action_space.n),
            group_n_actions=self.group_n_actions,
            features_extractor=None
            if extractor_class is None
            else lambda: extractor_class(obs_space, **extractor_kwargs),
            **options,
        )

    @property
    def recurrent_networks(self) -> list[HGRN]:
        """The networks whose recurrent states are carried between steps, in state order."""
        raise NotImplementedError

    @property
    def state_dim(self) -> int:
        """Width of the carried per-agent state (0 without recurrence)."""
        return sum(network.state_dim for network in self.recurrent_networks)

    def split_state(self, state: th.Tensor) -> list[th.Tensor]:
        """Split a carried state ``(..., state_dim)`` into one state per recurrent network."""
        return list(state.split([network.state_dim for network in self.recurrent_networks], dim=-1))

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.update(
            self.network_kwargs,
            lr_schedule=self.lr_schedule,
            stochastic=self.stochastic,
            alpha_log_space=self.alpha_log_space,
            group_n_actions=self.group_n_actions,
            average_tau=self.average_tau,
        )
        return data

    # --- the deployed network -----------------------------------------------------------------
    @property
    def online_network(self) -> HGRN:
        """The acting network being trained: it collects the experience."""
        return getattr(self, self.acting_network_name)

    @property
    def average_network(self) -> nn.Module | None:
        """The Polyak average of :attr:`online_network` (``None`` without ``average_tau``)."""
        return getattr(self, f"{self.acting_network_name}_average", None)

    @property
    def deployed_network(self) -> nn.Module:
        """The network :meth:`act` (``predict``, every evaluation) acts with: the average when one is
        kept, else the online network."""
        average = self.average_network
        return self.online_network if average is None else average

    @property
    def deployed_label(self) -> str:
        """What :meth:`act` acts with, in words, e.g. ``"Polyak average of the Q-network"``."""
        if self.average_network is None:
            return f"online {self.acting_network_label}"
        return f"Polyak average of the {self.acting_network_label}"

    def keep_average(self) -> None:
        """Start the Polyak average of :attr:`online_network` when ``average_tau`` is set (subclasses
        call it once the network is built)."""
        average = None if self.average_tau is None else polyak_average(self.online_network, self.average_tau)
        setattr(self, f"{self.acting_network_name}_average", average)

    def update_average(self) -> None:
        """Add the online acting network's weights to the average (no-op without ``average_tau``)."""
        average = self.average_network
        if average is not None:
            average.update_parameters(self.online_network)

    def drop_average(self) -> None:
        """Forget the averaged network: act with the online one from now on."""
        self.average_tau = None
        self.keep_average()

    # --- graph batches ------------------------------------------------------------------------
    def to_graphs(self, obs: GraphObs) -> tuple[th.Tensor, th.Tensor, th.Tensor | None]:
        """Slot batch -> graphs.

        :param obs: ``{"obs": (n_slots, *obs_shape), "neighbors": (n_slots, K)}`` tensors (and
            ``"group": (n_slots,)`` with agent groups).
        :return: observations ``(n_graphs, n_agents, *obs_shape)`` float32, neighbours
            ``(n_graphs, n_agents, K)`` int64 and group ids ``(n_graphs, n_agents)`` int64 (``None``
            for one group).
        """
        n_slots = obs["obs"].shape[0]
        n_agents = self.n_agents
        if n_agents is None:
            raise RuntimeError(NO_AGENT_COUNT)
        if n_slots % n_agents != 0:
            raise ValueError(
                f"A batch of {n_slots} observations is not a whole number of graphs of {n_agents} "
                "agents; predict() takes the observations of all slots of the graph VecEnv."
            )
        n_graphs = n_slots // n_agents
        groups = obs.get("group")
        return (
            obs["obs"].reshape(n_graphs, n_agents, *obs["obs"].shape[1:]).float(),
            obs["neighbors"].reshape(n_graphs, n_agents, -1).long(),
            None if groups is None else groups.reshape(n_graphs, n_agents).long(),
        )

    def graph_batch(self, neighbors: th.Tensor, groups: th.Tensor | None) -> GraphBatch:
        """The prepared graphs of :meth:`to_graphs`' neighbours ``(n_graphs, n_agents, K)`` and group
        ids ``(n_graphs, n_agents)`` (or ``None``): build it once and pass it, in place of the
        neighbours, to every network reading these graphs."""
        return GraphBatch(neighbors, groups, self.n_groups)

    def act(
        self, obs: GraphObs, hidden: th.Tensor, deterministic: bool = False
    ) -> tuple[th.Tensor, th.Tensor]:
        """Choose actions for a slot batch with the :attr:`deployed_network`.

        :param obs: slot batch of graph observations (see :meth:`to_graphs`).
        :param hidden: ``(n_slots, state_dim)`` recurrent state.
        :return: actions ``(n_slots,)`` and the new state ``(n_slots, state_dim)``.
        """
        return self.act_with(self.deployed_network, obs, hidden, deterministic)

    def act_with(
        self, network: nn.Module, obs: GraphObs, hidden: th.Tensor, deterministic: bool = False
    ) -> tuple[th.Tensor, th.Tensor]:
        """As :meth:`act`, with ``network`` (the online acting network or its average) choosing."""
        raise NotImplementedError

    def forward(self, obs: GraphObs, deterministic: bool = False) -> th.Tensor:
        """Actions ``(n_slots,)`` for a slot batch, starting from a zero recurrent state."""
        return self._predict(obs, deterministic)

    def _predict(self, observation: GraphObs, deterministic: bool = False) -> th.Tensor:
        hidden = th.zeros(observation["obs"].shape[0], self.state_dim, device=self.device)
        return self.act(observation, hidden, deterministic)[0]

    def predict(
        self,
        observation: dict[str, np.ndarray],
        state: tuple[np.ndarray, ...] | None = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = False,
    ) -> tuple[np.ndarray, tuple[np.ndarray, ...]]:
        """Actions for all slots, with the recurrent state threaded as in sb3-contrib's RecurrentPPO.

        :param observation: ``{"obs": (n_slots, *obs_shape), "neighbors": (n_slots, K)}``.
        :param state: ``(hidden,)`` with ``hidden`` of shape ``(1, n_slots, state_dim)``; ``None``
            starts from zeros.
        :param episode_start: ``(n_slots,)``, true where ``observation`` is the first of an episode
            (its state is reset to zero).
        :return: actions ``(n_slots,)`` and the new state ``(hidden,)``.
        :raises TypeError: for an ``observation`` that is no dict of arrays of numbers, a ``state`` or
            ``episode_start`` that holds no numbers.
        :raises ValueError: naming the slot for a NaN, infinite or out-of-space observation, a bad
            neighbour index or a NaN or infinite state (checked on the numpy arrays), and stating the
            expected keys and shapes for an ``observation``, ``state`` or ``episode_start`` that does not
            fit the batch.
        """
        if self.training or self.deployed_network.training:  # switching walks every module
            self.set_training_mode(False)
            self.deployed_network.train(False)  # an average, which set_training_mode leaves alone
        check_graph_batch(observation, self.observation_space)
        self._check_observations(observation)
        obs_tensor, _ = self.obs_to_tensor(observation)
        hidden = self._initial_state(state, episode_start, obs_tensor["obs"].shape[0])
        with th.inference_mode():  # acting records no graph: torch's cheapest mode, about 10 % off a step
            actions, new_hidden = self.act(
                obs_tensor, th.as_tensor(hidden, dtype=th.float32, device=self.device), deterministic
            )
        return actions.cpu().numpy(), (new_hidden.cpu().numpy()[None],)

    def _check_observations(self, observation: dict[str, np.ndarray]) -> None:
        """Raise a ``ValueError`` naming the first slot of a slot batch whose observation is bad (see
        :func:`~sb3_hgrn.common.checks.observation_problem`)."""
        if self.n_agents is None:
            raise RuntimeError(NO_AGENT_COUNT)
        problem = observation_problem(observation, self.observation_space["obs"], self.n_agents)
        if problem is not None:
            slot, what = problem
            raise ValueError(
                f"predict() got {what} for {slot_name(slot, self.n_agents)} in the observations of this call."
            )

    def _initial_state(
        self, state: tuple[np.ndarray, ...] | None, episode_start: np.ndarray | None, n_slots: int
    ) -> np.ndarray:
        """The recurrent state ``(n_slots, state_dim)`` fed in by :meth:`predict`: ``state``'s (zero
        without one), reset where ``episode_start`` is true; a ``ValueError`` states the expected
        shapes when either does not fit the batch."""
        expected = (1, n_slots, self.state_dim)
        if state is None:
            hidden = np.zeros(expected[1:], dtype=np.float32)
        else:
            if not isinstance(state, tuple | list) or len(state) != 1:
                given = (
                    f"an array of shape {state.shape}" if isinstance(state, np.ndarray) else repr(state)[:80]
                )
                raise ValueError(
                    f"state must be the tuple (hidden,) returned by the previous predict(), with hidden of "
                    f"shape {expected} (1, n_slots, state_dim), or None; got {given}."
                )
            hidden = np.asarray(state[0])
            if hidden.shape != expected:
                raise ValueError(
                    f"state[0] has shape {hidden.shape}, expected {expected} (1, n_slots, state_dim) for "
                    f"this batch of {n_slots} slots."
                )
            hidden = hidden[0]
            check_state(hidden, self.n_agents)
        if episode_start is not None:
            starts = np.asarray(episode_start)
            if starts.shape != (n_slots,):
                raise ValueError(
                    f"episode_start has shape {starts.shape}, expected ({n_slots},): one flag per slot."
                )
            if starts.dtype.kind not in "biuf":
                raise TypeError(f"episode_start must hold booleans (or 0 and 1), got dtype {starts.dtype}.")
            flags = np.isin(starts, (0, 1))
            if not flags.all():
                raise ValueError(f"episode_start must hold booleans (or 0 and 1), got {starts[~flags][0]}.")
            hidden = hidden * (1.0 - starts.astype(np.float32))[:, None]
        return hidden
