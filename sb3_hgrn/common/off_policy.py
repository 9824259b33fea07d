"""Common base of the graph algorithms: SB3's off-policy loop with recurrent state and team episodes."""

from __future__ import annotations

import io
import math
import os
import pathlib
import random
import sys
import time
from collections import deque
from collections.abc import Iterable, Mapping
from typing import Any, ClassVar

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common import torch_layers as sb3_torch_layers
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.type_aliases import GymEnv, RolloutReturn, Schedule, TrainFreq
from stable_baselines3.common.utils import (
    LinearSchedule,
    check_for_correct_spaces,
    safe_mean,
    should_collect_more_steps,
)
from stable_baselines3.common.vec_env import VecEnv

from sb3_hgrn.common import torch_layers
from sb3_hgrn.common.arguments import argument_hints, check_argument_types, named_parameters
from sb3_hgrn.common.attention import GraphBatch
from sb3_hgrn.common.buffers import GraphReplayBuffer, GraphSamples
from sb3_hgrn.common.checks import check_rewards
from sb3_hgrn.common.files import (
    ModelFileError,
    ZipSource,
    check_model_file,
    check_policy_settings,
    describe_saved_model,
    saved_data,
    saved_policy_module,
)
from sb3_hgrn.common.hgrn import HGRN
from sb3_hgrn.common.memory import keep_freed_memory
from sb3_hgrn.common.policies import GraphPolicy, check_graph_spaces, check_policy_kwargs
from sb3_hgrn.common.safe_load import add_plain_record, read_saved_pickle, saved_entries, write_zip
from sb3_hgrn.common.temperature import TemperatureLearner
from sb3_hgrn.common.tensorboard import AlgorithmNamedRuns
from sb3_hgrn.common.vec_env import make_graph_vec_env
from sb3_hgrn.validation import is_integer, is_number

TRAINING_STATE_KEYS = frozenset(
    "num_timesteps env last_obs last_episode_starts last_hidden team_episodes "
    "torch_rng cuda_rng numpy_rng python_rng".split()
)
"""The entries every :meth:`GraphOffPolicyAlgorithm.get_training_state` holds (its ``last_alive``,
the agents alive in the last observation, may be missing from older states: all were alive then)."""


GRAPH_MODEL_KEYS = frozenset({"target_entropy_ratio", "hidden_dtype", "n_agents"})
"""Entries of the ``data`` of every zip a :class:`GraphOffPolicyAlgorithm` saves."""


def check_graph_env(env: Any) -> VecEnv:
    """Return ``env`` as a graph VecEnv, or raise an error that names what is wrong with it.

    A registered env name is turned into a one-copy graph VecEnv (as SB3 makes an env from a name).
    """
    if isinstance(env, str):
        return make_graph_vec_env(env)
    if not isinstance(env, VecEnv):
        raise TypeError(
            f"Expected a graph VecEnv (sb3_hgrn.make_graph_vec_env), got {type(env).__name__}; "
            "single-agent gymnasium envs are not supported."
        )
    if not isinstance(getattr(env, "n_agents", None), int) or env.num_envs % env.n_agents != 0:
        raise TypeError(
            f"{type(env).__name__} is not a graph VecEnv: it needs an integer n_agents attribute with "
            "num_envs a multiple of it (build it with sb3_hgrn.make_graph_vec_env)."
        )
    check_graph_spaces(env.observation_space, env.action_space)
    return env


def concatenated(steps: list[GraphSamples]) -> GraphSamples:
    """The samples of consecutive steps (each ``batch`` graphs) as one batch of ``steps * batch``
    graphs, step-major (single steps are returned as they are, without a copy)."""
    if len(steps) == 1:
        return steps[0]
    return GraphSamples(
        *(None if fields[0] is None else th.cat(fields) for fields in zip(*steps, strict=True))
    )


def unroll(
    network: HGRN, observations: th.Tensor, graph: GraphBatch, state: th.Tensor, starts: list[th.Tensor]
) -> th.Tensor:
    """Outputs ``(steps * batch, n_agents, n_outputs)`` of ``network`` along runs of consecutive
    samples, step-major (as :func:`concatenated`), its recurrent state carried from ``state``
    ``(batch, n_agents, state_dim)`` (the stored state of the first step) through the run, so that
    gradients flow back through time, and restarted from zero where a step's ``starts`` flags the
    first step of an episode.

    The layers before the memory read no state, so they run once over every step's graphs together
    (:meth:`~sb3_hgrn.common.hgrn.HGRN.features`); only the GRU steps through time.

    :param observations: ``(steps * batch, n_agents, *obs_shape)``, step-major.
    :param graph: the prepared graphs of all steps' neighbours, step-major (``GraphPolicy.graph_batch``).
    :param starts: every step's ``(batch,)`` episode-start flags (the first step's are not read).
    """
    batch = state.shape[0]
    features = network.features(observations, graph)
    memories = []
    for index, step_starts in enumerate(starts):
        if index > 0:
            state = state * (~step_starts).to(state.dtype)[:, None, None]
        rows = slice(index * batch, (index + 1) * batch)
        memory = network.remember(features[rows], state, graph.block(index * batch, batch))
        state = memory if network.gru is not None else state
        memories.append(memory)
    return network.outputs(th.cat(memories), graph)


def check_algorithm_arguments(
    learning_rate: Any,
    buffer_size: Any,
    batch_size: Any,
    gamma: Any,
    train_freq: Any,
    n_agents: int | None = None,
    n_steps: Any = 1,
    sequence_length: Any = 1,
) -> None:
    """Raise a ``ValueError`` naming the argument unless the arguments make a model that trains.

    ``learning_rate`` is a positive number or a schedule (a callable), ``batch_size`` a positive
    integer (graphs), ``0 <= gamma <= 1``, ``n_steps`` a positive integer, ``sequence_length`` a
    positive integer that divides ``batch_size``, ``train_freq`` at least 1
    (vec-steps, or ``(n, unit)``) and ``buffer_size`` an integer of agent-transitions that holds at
    least one batch of graphs (``batch_size * n_agents``, when the env and so ``n_agents`` is known).
    """
    if not callable(learning_rate) and not (is_number(learning_rate) and learning_rate > 0):
        raise ValueError(
            f"learning_rate must be a positive number or a schedule (callable), got {learning_rate!r}."
        )
    if not is_integer(batch_size) or batch_size < 1:
        raise ValueError(
            f"batch_size must be a positive integer (graphs per gradient step), got {batch_size!r}."
        )
    if not is_number(gamma) or not 0 <= gamma <= 1:
        raise ValueError(f"gamma must be a number in [0, 1], got {gamma!r}.")
    if not is_integer(n_steps) or n_steps < 1:
        raise ValueError(f"n_steps must be a positive integer (steps per return), got {n_steps!r}.")
    if not is_integer(sequence_length) or sequence_length < 1 or batch_size % sequence_length:
        raise ValueError(
            f"sequence_length must be a positive integer that divides batch_size={batch_size} (a batch is "
            f"batch_size // sequence_length runs of sequence_length steps), got {sequence_length!r}."
        )
    frequency = train_freq[0] if isinstance(train_freq, tuple | list) and train_freq else train_freq
    if not is_integer(frequency) or frequency < 1:
        raise ValueError(
            f"train_freq must be an integer >= 1 (or a tuple (n >= 1, unit)), got {train_freq!r}."
        )
    if not is_integer(buffer_size) or buffer_size < 1:
        raise ValueError(f"buffer_size must be a positive integer (agent-transitions), got {buffer_size!r}.")
    if n_agents is not None and buffer_size < batch_size * n_agents:
        raise ValueError(
            f"buffer_size must hold at least one batch of graphs: batch_size * n_agents = {batch_size} * "
            f"{n_agents} = {batch_size * n_agents} agent-transitions, got {buffer_size}."
        )


AUTO_REWARD_SCALE = "auto"
"""``reward_scale="auto"``: the factor is measured from the replay buffer at the first gradient step
(``1 / max(1, RMS of the stored discounted returns)``)."""


def check_reward_scale(reward_scale: Any) -> None:
    """Raise a ``ValueError`` unless ``reward_scale`` is a finite number > 0 or ``"auto"``."""
    if reward_scale == AUTO_REWARD_SCALE:
        return
    if not is_number(reward_scale) or not math.isfinite(reward_scale) or reward_scale <= 0:
        raise ValueError(f'reward_scale must be a finite number > 0 or "auto", got {reward_scale!r}.')


def check_hidden_dtype(hidden_dtype: Any, prefix: str = "") -> None:
    """Raise a ``TypeError`` unless ``hidden_dtype`` names a numpy float dtype (the replay buffer's
    storage of recurrent states); ``prefix`` goes before the name in the message."""
    try:
        kind = np.dtype(hidden_dtype).kind
    except TypeError:
        kind = None
    if kind != "f":
        raise TypeError(
            f"{prefix}hidden_dtype must name a numpy float dtype for the recurrent states in the replay "
            f"buffer (float16, float32 or float64), got {hidden_dtype!r}."
        )


def check_model_arguments(
    algorithm: type[GraphOffPolicyAlgorithm], arguments: Mapping[str, Any], prefix: str = ""
) -> None:
    """Raise a ``TypeError`` naming the argument unless the numbers and flags among ``algorithm``'s
    ``arguments`` and their ``policy_kwargs`` have their annotated types (see
    :mod:`sb3_hgrn.common.arguments`), ``hidden_dtype`` names a float dtype and every entry of
    ``policy_kwargs`` is an argument of the policy (:func:`~sb3_hgrn.common.policies.check_policy_kwargs`).

    :param arguments: keyword arguments of ``algorithm`` by name (any subset of them).
    :param prefix: put before the argument names in the message (``"default."``: the section of a
        config file they come from).
    """
    check_argument_types(argument_hints(algorithm.__init__), arguments, prefix)
    if "hidden_dtype" in arguments:
        check_hidden_dtype(arguments["hidden_dtype"], prefix)
    policy = arguments.get("policy", "GraphPolicy")
    policy_class = algorithm.policy_aliases[policy] if isinstance(policy, str) else policy
    policy_kwargs = arguments.get("policy_kwargs") or {}
    check_policy_kwargs(policy_class, policy_kwargs, algorithm.__init__, f"{prefix}policy_kwargs")


def check_added_arguments(algorithm: type[GraphOffPolicyAlgorithm], arguments: Mapping[str, Any]) -> None:
    """Raise a ``TypeError`` naming the argument unless the numbers and flags among the arguments that
    ``algorithm`` adds to those of :class:`GraphOffPolicyAlgorithm` have their annotated types (as
    :func:`check_model_arguments` checks the shared ones, which the base constructor does itself).

    :param arguments: ``locals()`` at the start of ``algorithm.__init__``; names that are not its
        arguments are ignored.
    """
    shared = set(named_parameters(GraphOffPolicyAlgorithm.__init__))
    added = {name: value for name, value in arguments.items() if name not in shared}
    check_argument_types(argument_hints(algorithm.__init__), added)


def check_policy(policy: Any, aliases: dict[str, type]) -> None:
    """Raise an error naming the accepted values unless ``policy`` is a name in ``aliases`` (an
    algorithm's ``policy_aliases``) or a subclass of one of their classes (``TypeError`` for other
    kinds of values, ``ValueError`` for an unknown name)."""
    classes = tuple(aliases.values())
    accepted = (
        f"one of the names {', '.join(map(repr, aliases))} or a subclass of "
        f"{' or '.join(cls.__name__ for cls in classes)}"
    )
    if isinstance(policy, str):
        if policy not in aliases:
            raise ValueError(f"Unknown policy {policy!r}: policy must be {accepted}.")
    elif not (isinstance(policy, type) and issubclass(policy, classes)):
        raise TypeError(f"policy must be {accepted}, got {policy!r}.")


def _policy_modules(algorithm: type) -> set[str]:
    """Modules of the policy classes an algorithm names in its ``policy_aliases``."""
    return {policy.__module__ for policy in getattr(algorithm, "policy_aliases", {}).values()}


def _graph_algorithms() -> list[type[GraphOffPolicyAlgorithm]]:
    """Every subclass of :class:`GraphOffPolicyAlgorithm` defined so far."""
    found, todo = [], list(GraphOffPolicyAlgorithm.__subclasses__())
    while todo:
        algorithm = todo.pop()
        found.append(algorithm)
        todo += algorithm.__subclasses__()
    return found


def env_action_counts(env: VecEnv) -> list[int]:
    """Action count of every agent group of a graph VecEnv (one group unless it says otherwise)."""
    return [int(n) for n in getattr(env, "group_n_actions", (env.action_space.n,))]


class GraphOffPolicyAlgorithm(AlgorithmNamedRuns, TemperatureLearner, OffPolicyAlgorithm):
    """SB3 ``OffPolicyAlgorithm`` for graph VecEnvs whose slots are the agents of env copies.

    Units follow SB3: ``total_timesteps``, ``learning_starts`` and ``buffer_size`` count
    agent-steps (one vec-step of ``n_copies`` copies of ``n_agents`` agents is
    ``n_copies * n_agents`` of them), ``train_freq`` counts vec-steps, ``batch_size`` counts graphs,
    ``gradient_steps=-1`` takes one gradient step per graph collected (``n_copies`` per vec-step),
    ``target_update_interval`` counts gradient steps and ``log_interval`` counts team episodes (one
    per env copy).

    The recurrent state of every agent is threaded through collection (also during the random
    warm-up), reset at episode starts, and stored with each transition. Exploration mixes in a
    uniform random action per agent with probability ``exploration_rate``, scheduled linearly from
    ``exploration_initial_eps`` to ``exploration_final_eps`` over ``exploration_fraction`` of
    training (by default ``stochastic_exploration_eps`` throughout for stochastic policies, 1.0 -> 0.05
    for ``stochastic=False``).

    The soft algorithms share a temperature alpha learned toward the target entropy
    ``target_entropy_ratio * log(n_actions)`` (see :mod:`sb3_hgrn.common.temperature`); the policy
    owns it as ``policy.temperature``. ``learn_alpha=False`` keeps alpha at ``alpha_init``.

    Heterogeneous envs (several agent groups) give every group its own network parameters, its own
    alpha and its own target entropy from its own action count; exploration and sampling never pick
    an action outside the agent's group, and targets never bootstrap through one.
    """

    policy: GraphPolicy
    replay_buffer: GraphReplayBuffer
    stochastic_exploration_eps: ClassVar[float] = 0.3
    """Epsilon of a stochastic policy when ``exploration_initial_eps``/``_final_eps`` are ``None``: 30 %
    of each agent's actions uniform while collecting, the level of the original code's test mode
    (docs/results_defaults.md)."""
    reward_scale: float | str
    """The ``reward_scale`` argument."""
    applied_reward_scale: float = 1.0
    """The factor the targets apply to the rewards (``"auto"``'s is measured at the first update)."""
    defaults_before_saved: ClassVar[dict[str, Any]] = {"reward_scale": 1.0}
    """Attributes whose default changed after models were saved without them, with the value such a
    model trained with: :meth:`load` gives it that value instead of today's default (models saved
    before ``reward_scale`` existed trained on the env's own rewards)."""
    policy_settings: ClassVar[tuple[str, ...]] = ("stochastic",)
    """Arguments the policy is built with too: :meth:`load` refuses values other than the saved ones."""

    def __init__(
        self,
        policy: str | type[GraphPolicy],
        env: GymEnv | str | None,
        learning_rate: float | Schedule,
        buffer_size: int,
        learning_starts: int,
        batch_size: int,
        tau: float,
        gamma: float,
        reward_scale: float | str,
        n_steps: int,
        sequence_length: int,
        train_freq: int | tuple[int, str],
        gradient_steps: int,
        target_update_interval: int,
        target_entropy_ratio: float,
        alpha_init: float | str,
        learn_alpha: bool,
        alpha_optimizer: str,
        alpha_learning_rate: float,
        alpha_max_step: float,
        stochastic: bool,
        exploration_fraction: float,
        exploration_initial_eps: float | None,
        exploration_final_eps: float | None,
        max_grad_norm: float,
        hidden_dtype: str,
        policy_kwargs: dict[str, Any] | None,
        stats_window_size: int,
        tensorboard_log: str | None,
        verbose: int,
        seed: int | None,
        device: th.device | str,
    ):
        arguments = dict(locals())
        check_policy(policy, self.policy_aliases)
        if env is not None:
            env = check_graph_env(env)
        check_algorithm_arguments(
            learning_rate,
            buffer_size,
            batch_size,
            gamma,
            train_freq,
            env.n_agents if env is not None else None,
            n_steps,
            sequence_length,
        )
        check_model_arguments(type(self), arguments)
        check_reward_scale(reward_scale)
        if exploration_initial_eps is None:
            exploration_initial_eps = self.stochastic_exploration_eps if stochastic else 1.0
        if exploration_final_eps is None:
            exploration_final_eps = self.stochastic_exploration_eps if stochastic else 0.05
        super().__init__(
            policy,
            env,
            learning_rate,
            buffer_size=buffer_size,
            learning_starts=learning_starts,
            batch_size=batch_size,
            tau=tau,
            gamma=gamma,
            train_freq=train_freq,
            gradient_steps=gradient_steps,
            n_steps=n_steps,
            policy_kwargs={**(policy_kwargs or {}), "stochastic": stochastic},
            stats_window_size=stats_window_size,
            tensorboard_log=tensorboard_log,
            verbose=verbose,
            device=device,
            support_multi_env=True,
            monitor_wrapper=False,
            seed=seed,
            sde_support=False,
            supported_action_spaces=(spaces.Discrete,),
        )
        self.sequence_length = sequence_length
        self.target_update_interval = target_update_interval
        self.reward_scale = reward_scale
        self.applied_reward_scale = 1.0 if reward_scale == AUTO_REWARD_SCALE else float(reward_scale)
        self._set_temperature_options(
            target_entropy_ratio,
            alpha_init,
            learn_alpha,
            alpha_optimizer,
            alpha_learning_rate,
            alpha_max_step,
        )
        self.stochastic = stochastic
        self.exploration_fraction = exploration_fraction
        self.exploration_initial_eps = exploration_initial_eps
        self.exploration_final_eps = exploration_final_eps
        self.exploration_rate = exploration_initial_eps
        self.max_grad_norm = max_grad_norm
        self.hidden_dtype = hidden_dtype
        self.n_agents = env.n_agents if env is not None else None
        if env is not None and len(env_action_counts(env)) > 1:
            self.policy_kwargs["group_n_actions"] = env_action_counts(env)
        self._last_hidden: np.ndarray | None = None
        self._last_alive: np.ndarray | None = None  # (n_envs,) bool, the agents alive in _last_obs
        self._team_episodes: deque = deque(maxlen=stats_window_size)

    # --- model set-up -------------------------------------------------------------------------
    def _setup_model(self) -> None:
        self._setup_lr_schedule()
        self.set_random_seed(self.seed)
        if self.env is not None:
            self.n_agents = self.env.n_agents
        self.policy = self.policy_class(
            self.observation_space, self.action_space, self.lr_schedule, **self.policy_kwargs
        ).to(self.device)
        self.policy.n_agents = self.n_agents
        self.replay_buffer = None
        if self.env is not None:
            self._make_replay_buffer()
        self._convert_train_freq()
        self.exploration_schedule = LinearSchedule(
            self.exploration_initial_eps, self.exploration_final_eps, self.exploration_fraction
        )
        self._team_episodes = deque(maxlen=self._stats_window_size)
        self._setup_temperature()

    def _sample_runs(self, batch_size: int) -> tuple[GraphSamples, list[GraphSamples]]:
        """The ``batch_size`` graphs of one gradient step: ``batch_size // sequence_length`` runs of
        ``sequence_length`` consecutive steps, as one step-major batch (its rewards times
        :attr:`applied_reward_scale`, for the targets) and as the list of its steps (for
        :func:`unroll`)."""
        steps = self.replay_buffer.sample_sequences(batch_size // self.sequence_length, self.sequence_length)
        batch = concatenated(steps)
        return batch._replace(rewards=batch.rewards * self.applied_reward_scale), steps

    def _start_training(self) -> None:
        """Before the first gradient step: with ``reward_scale="auto"``, measure the factor of the
        rewards from the replay buffer: one over the root mean square of its discounted returns
        (:meth:`~sb3_hgrn.common.buffers.GraphReplayBuffer.return_rms`) where that is above 1, else 1
        (returns larger than one are shrunk, smaller ones left as they are). Then set up the
        temperature (:meth:`_start_temperature`). Resumed models keep their factor."""
        if self.reward_scale == AUTO_REWARD_SCALE and self._n_updates == 0:
            self.applied_reward_scale = 1.0 / max(1.0, self.replay_buffer.return_rms(self.gamma))
        self.logger.record("train/reward_scale", self.applied_reward_scale)
        self._start_temperature()

    def _stored_rewards(self) -> np.ndarray:
        """The stored rewards as the targets see them: times :attr:`applied_reward_scale`."""
        return super()._stored_rewards() * self.applied_reward_scale

    def _learns_alpha(self) -> bool:
        """Whether training steps alpha: only the stochastic variants learn it."""
        return self.stochastic and self.learn_alpha

    def _make_replay_buffer(self) -> None:
        self.replay_buffer = GraphReplayBuffer(
            self.buffer_size,
            self.observation_space,
            self.action_space,
            device=self.device,
            n_envs=self.n_envs,
            n_agents=self.n_agents,
            state_dim=self.policy.state_dim,
            hidden_dtype=self.hidden_dtype,
            n_steps=self.n_steps,
            gamma=self.gamma,
        )

    def set_env(self, env: GymEnv, force_reset: bool = True) -> None:
        """Attach another graph VecEnv (any number of copies or agents, the same spaces); the env is
        reset before training when its graphs differ in size."""
        env = check_graph_env(env)
        check_for_correct_spaces(env, self.observation_space, self.action_space)
        if env_action_counts(env) != self.policy.action_counts:
            raise ValueError(
                f"The env's agent groups have {env_action_counts(env)} actions, the model's "
                f"{self.policy.action_counts}."
            )
        resized = env.num_envs != self.n_envs or env.n_agents != self.n_agents
        self.n_envs = env.num_envs  # SB3 asserts an unchanged slot count; graphs may change size
        super().set_env(env, force_reset=force_reset or resized)
        self.n_agents = env.n_agents
        self.policy.n_agents = env.n_agents
        buffer = self.replay_buffer
        if buffer is None or buffer.n_envs != env.num_envs or buffer.n_agents != env.n_agents:
            self._make_replay_buffer()
        self._last_hidden = None
        self._last_alive = None

    @staticmethod
    def _wrap_env(env: GymEnv, verbose: int = 0, monitor_wrapper: bool = True) -> VecEnv:
        return check_graph_env(env)

    def save(
        self,
        path: str | pathlib.Path | io.BufferedIOBase,
        exclude: Iterable[str] | None = None,
        include: Iterable[str] | None = None,
    ) -> None:
        """SB3's ``save``, with the plain-data record of what SB3 pickles (see
        :mod:`sb3_hgrn.common.safe_load`), so that :meth:`load` rebuilds the model without unpickling."""
        self._sync_policy_kwargs()
        archive = io.BytesIO()
        super().save(archive, exclude, include)
        add_plain_record(archive, self.__dict__)
        write_zip(path, archive.getvalue())

    def _sync_policy_kwargs(self) -> None:
        """Make ``policy_kwargs`` describe the policy as it is now, so that a loaded model builds the
        same one: ``average_tau`` is ``None`` once ``policy.drop_average()`` dropped the average."""
        if self.policy_kwargs.get("average_tau") != self.policy.average_tau:
            self.policy_kwargs = {**self.policy_kwargs, "average_tau": self.policy.average_tau}

    @classmethod
    def load(
        cls,
        path: str | os.PathLike | io.BufferedIOBase,
        env: GymEnv | None = None,
        device: th.device | str = "auto",
        custom_objects: dict[str, Any] | None = None,
        print_system_info: bool = False,
        force_reset: bool = True,
        trust_pickle: bool = False,
        **kwargs: Any,
    ):
        """SB3's ``load``, without running code from the file unless ``trust_pickle``.

        The settings SB3 pickles are rebuilt from plain data (:mod:`sb3_hgrn.common.safe_load`) and
        the weights read with ``torch.load(weights_only=True)``. A zip with an entry that only full
        unpickling can rebuild (a learning-rate function, a policy class of one's own) raises
        :class:`~sb3_hgrn.common.safe_load.UntrustedPickleError` naming it; ``trust_pickle=True``
        unpickles it as SB3 does, which can run any code: pass it only for files you trust.

        :raises FileNotFoundError: naming ``path`` when neither it nor ``<path>.zip`` is a file.
        :raises ~sb3_hgrn.common.files.DamagedModelFileError: for a damaged zip (cut short, not a
            zip, unreadable contents), naming the file.
        :raises ~sb3_hgrn.common.files.ModelFileError: for a zip of another library's algorithm.
        :raises ValueError: for a zip of another sb3_hgrn algorithm, naming the class to load it with,
            and for a ``kwargs`` value of one of :attr:`policy_settings` other than the saved one.

        A given ``env`` keeps its own seeds: the model is loaded without it (SB3 would reseed it with
        the model's seed) and then attached with :meth:`set_env`.
        """
        if isinstance(path, str | os.PathLike):
            source, name = check_model_file(path), os.fspath(path)
        else:
            source, name = io.BytesIO(path.read()), "the model file"
        cls._check_saved_algorithm(source, name)
        if not trust_pickle:
            given = custom_objects or {}
            custom_objects = {**saved_entries(source, name, cls._loadable_classes(), skip=given), **given}
        model = super().load(source, None, device, custom_objects, print_system_info, force_reset, **kwargs)
        saved = saved_data(source).keys() | kwargs.keys()
        for name, value in cls.defaults_before_saved.items():
            if name not in saved:
                setattr(model, name, value)
        check_policy_settings(model, cls.policy_settings)
        if env is not None:
            model.set_env(env, force_reset=force_reset)
        return model

    @classmethod
    def _loadable_classes(cls) -> list[type]:
        """The classes a model file may name when it is loaded without trust: the algorithm's policy
        classes, torch's optimisers and the features extractors of sb3_hgrn and SB3."""

        def subclasses(module: Any, base: type) -> list[type]:
            return [
                value
                for value in vars(module).values()
                if isinstance(value, type) and issubclass(value, base)
            ]

        extractors = [
            *subclasses(sb3_torch_layers, sb3_torch_layers.BaseFeaturesExtractor),
            *subclasses(torch_layers, sb3_torch_layers.BaseFeaturesExtractor),
        ]
        return [*cls.policy_aliases.values(), *subclasses(th.optim, th.optim.Optimizer), *extractors]

    @classmethod
    def _check_saved_algorithm(cls, source: ZipSource, name: str) -> None:
        """Raise an error saying what saved ``source`` unless it holds a model of this algorithm (known
        by its policy's module): a ``ValueError`` naming the class to load it with for another graph
        algorithm, a :class:`~sb3_hgrn.common.files.ModelFileError` for another library's model."""
        module = saved_policy_module(source)
        if module in _policy_modules(cls):
            return
        for other in _graph_algorithms():
            if module in _policy_modules(other):
                raise ValueError(
                    f"{name} holds a {other.__name__} model, not a {cls.__name__} one: load it with "
                    f"{other.__name__}.load."
                )
        if GRAPH_MODEL_KEYS <= set(saved_data(source)):  # a graph model with a policy class of its own
            return
        raise ModelFileError(
            f"{name} is not an sb3_hgrn model: it was saved by {describe_saved_model(source)}. Load it "
            "with that algorithm's own class."
        )

    def load_replay_buffer(
        self,
        path: str | pathlib.Path | io.BufferedIOBase,
        truncate_last_traj: bool = True,
        trust_pickle: bool = False,
    ) -> None:
        """Load a :class:`GraphReplayBuffer` written by ``save_replay_buffer`` (also by another
        instance of this model, e.g. before a ``load``).

        The buffer must have been filled on the model's slot layout (``n_envs`` slots of
        ``n_agents``-agent copies) with its observation shape and recurrent-state width; anything
        else raises a ``ValueError`` saying what differs. ``truncate_last_traj`` is SB3's
        ``HerReplayBuffer`` option and has no effect here.

        The file (a pickle) is read by :func:`~sb3_hgrn.common.safe_load.restricted_loads`, which
        builds only a buffer's own types; ``trust_pickle=True`` unpickles it in full (it can then
        run code: only for files you trust).

        :raises FileNotFoundError: naming ``path`` when neither it nor ``<path>.pkl`` is a file.
        :raises ~sb3_hgrn.common.files.DamagedModelFileError: for a file cut short or not a pickle.
        :raises ~sb3_hgrn.common.safe_load.UntrustedPickleError: for a file that refers to other
            types (another library's buffer), naming the first one.
        """
        buffer = read_saved_pickle(path, "replay buffer", ".pkl", trust_pickle, [GraphReplayBuffer])
        if not isinstance(buffer, GraphReplayBuffer):
            raise TypeError(f"{path} holds a {type(buffer).__name__}, not a GraphReplayBuffer.")
        layout = {
            "slots": (buffer.n_envs, self.n_envs),
            "agents per copy": (buffer.n_agents, self.n_agents),
            "observation shape": (buffer.observations.shape[3:], self.observation_space["obs"].shape),
            "recurrent-state width": (buffer.hidden.shape[-1], self.policy.state_dim),
        }
        differences = [
            f"{name} {saved} (model {own})" for name, (saved, own) in layout.items() if saved != own
        ]
        if differences:
            raise ValueError(
                f"The replay buffer in {path} does not fit this model: {', '.join(differences)}."
            )
        buffer.device = self.device
        buffer.n_steps, buffer.gamma = self.n_steps, self.gamma  # the model's returns, not the saver's
        self.replay_buffer = buffer

    def get_training_state(self) -> dict[str, Any]:
        """What a model zip and its replay buffer leave out of a run in progress, so that
        :meth:`set_training_state` resumes it exactly: the env's state (:meth:`GraphVecEnv.get_state
        <sb3_hgrn.common.vec_env.GraphVecEnv.get_state>`, a pickle), the last observation, episode
        starts ``(n_envs,)`` and recurrent state ``(n_envs, state_dim)``, the recent team episodes of
        the logs and the random states of torch, numpy and Python.

        Take it between two rounds of ``collect_rollouts`` (where ``learn`` has trained on all it
        collected): inside one, the last vec-step is not stored yet. Raises
        :class:`~sb3_hgrn.common.vec_env.UnpicklableEnvError` when the env cannot be pickled.
        """
        if self.env is None or self._last_obs is None:
            raise ValueError("The model has no env in progress to take the training state of.")
        return {
            "num_timesteps": self.num_timesteps,
            "env": self.env.get_state(),
            "last_obs": {key: value.copy() for key, value in self._last_obs.items()},
            "last_episode_starts": self._last_episode_starts.copy(),
            "last_hidden": self._last_hidden.copy(),
            "last_alive": self._last_alive.copy(),
            "team_episodes": list(self._team_episodes),
            "torch_rng": th.get_rng_state().numpy(),
            "cuda_rng": [state.numpy() for state in th.cuda.get_rng_state_all()]
            if th.cuda.is_initialized()
            else [],
            "numpy_rng": np.random.get_state(),
            "python_rng": random.getstate(),
        }

    def set_training_state(self, state: dict[str, Any], trust_pickle: bool = False) -> None:
        """Restore a :meth:`get_training_state` into this model (loaded from the zip saved with it),
        so that ``learn(..., reset_num_timesteps=False)`` goes on as the saved run would have.

        The env's state is unpickled as :meth:`GraphVecEnv.set_state
        <sb3_hgrn.common.vec_env.GraphVecEnv.set_state>` does it, in full only with ``trust_pickle``.

        A state that lacks an entry or was taken at another step than the model's ``num_timesteps``
        raises a ``ValueError``, one of another env layout too (before anything has changed).
        """
        missing = sorted(TRAINING_STATE_KEYS - set(state))
        if missing:
            raise ValueError(f"The training state lacks {', '.join(missing)}.")
        if state["num_timesteps"] != self.num_timesteps:
            raise ValueError(
                f"The training state was taken at agent-step {state['num_timesteps']}, the model is at "
                f"{self.num_timesteps}."
            )
        self.env.set_state(state["env"], trust_pickle)  # checks the layout before it changes anything
        self._last_obs = state["last_obs"]
        self._last_episode_starts = state["last_episode_starts"]
        self._last_hidden = state["last_hidden"]
        self._last_alive = state.get("last_alive", np.ones(self.n_envs, dtype=bool))
        self._team_episodes.clear()
        self._team_episodes.extend(state["team_episodes"])
        th.set_rng_state(th.from_numpy(state["torch_rng"]))
        if state["cuda_rng"] and th.cuda.is_available():
            th.cuda.set_rng_state_all([th.from_numpy(rng) for rng in state["cuda_rng"]])
        np.random.set_state(state["numpy_rng"])
        random.setstate(state["python_rng"])

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        return ["policy", *self._optimizer_names(), "temperature.optimizer"], []

    def _optimizer_names(self) -> list[str]:
        """Attribute paths of the network optimisers to save (``policy.optimizer`` by default)."""
        return ["policy.optimizer"]

    def _excluded_save_params(self) -> list[str]:
        return [
            *super()._excluded_save_params(),
            "_last_hidden",
            "_last_alive",
            "_team_episodes",
            "exploration_schedule",
        ]

    # --- collection -----------------------------------------------------------------------------
    def _setup_learn(self, total_timesteps, callback=None, reset_num_timesteps=True, tb_log_name="run",
                     progress_bar=False):  # fmt: skip
        if self.replay_buffer is None:
            self._make_replay_buffer()
        if self.device.type == "cpu":
            keep_freed_memory()  # large tensors of a gradient step reuse memory instead of faulting it in
        reset = reset_num_timesteps or self._last_obs is None
        result = super()._setup_learn(
            total_timesteps, callback, reset_num_timesteps, tb_log_name, progress_bar
        )
        if reset or self._last_hidden is None or self._last_hidden.shape[0] != self.n_envs:
            self._last_hidden = np.zeros((self.n_envs, self.policy.state_dim), dtype=np.float32)
            self._last_episode_starts = np.ones(self.n_envs, dtype=bool)
        if reset or self._last_alive is None or self._last_alive.shape[0] != self.n_envs:
            self._last_alive = self.env.alive
        return result

    def _choose_actions(self, hidden: np.ndarray, learning_starts: int) -> tuple[np.ndarray, np.ndarray]:
        """Exploration actions ``(n_envs,)`` and the new recurrent state ``(n_envs, state_dim)``."""
        obs_tensor, _ = self.policy.obs_to_tensor(self._last_obs)
        with th.inference_mode():  # as predict: no graph, no autograd bookkeeping
            actions, new_hidden = self._behaviour_act(obs_tensor, th.as_tensor(hidden, device=self.device))
        actions = actions.cpu().numpy()
        mask = self._last_obs.get("action_mask")
        n_actions = int(self.action_space.n) if mask is None else mask.sum(axis=1)  # per slot
        if self.num_timesteps < learning_starts:
            actions = np.random.randint(0, n_actions, size=self.n_envs)
        elif self.exploration_rate > 0:
            explore = np.random.random(self.n_envs) < self.exploration_rate
            actions = np.where(explore, np.random.randint(0, n_actions, size=self.n_envs), actions)
        return actions, new_hidden.cpu().numpy()

    def _behaviour_act(self, obs: dict[str, th.Tensor], hidden: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        """The online acting network's sampled actions ``(n_envs,)`` to collect with, before
        epsilon-random ones, and the new recurrent state ``(n_envs, state_dim)``."""
        return self.policy.act_with(self.policy.online_network, obs, hidden, deterministic=False)

    def _final_observations(self, new_obs: dict[str, np.ndarray], dones: np.ndarray, infos: list[dict]):
        """Next observations with each ended episode's final observation in place of its reset one."""
        if not dones.any():
            return new_obs
        next_obs = {key: value.copy() for key, value in new_obs.items()}
        n = self.n_agents
        for first_slot in np.flatnonzero(dones[::n]) * n:
            slots = slice(first_slot, first_slot + n)
            for key, value in infos[first_slot]["team_episode"]["final_observation"].items():
                next_obs[key][slots] = value
        return next_obs

    def collect_rollouts(
        self,
        env: VecEnv,
        callback: BaseCallback,
        train_freq: TrainFreq,
        replay_buffer: GraphReplayBuffer,
        action_noise: None = None,
        learning_starts: int = 0,
        log_interval: int | None = None,
    ) -> RolloutReturn:
        """Step all env copies ``train_freq`` times, storing whole graphs with their recurrent state.

        The returned step count is the number of graphs collected (vec-steps x copies): SB3's
        ``gradient_steps=-1`` then takes one gradient step per graph, as ``batch_size`` counts graphs.
        """
        self.policy.set_training_mode(False)
        vec_steps, n_episodes = 0, 0
        n_copies = env.num_envs // self.n_agents
        callback.on_rollout_start()
        while should_collect_more_steps(train_freq, vec_steps, n_episodes):
            hidden_in = self._last_hidden * (1.0 - self._last_episode_starts)[:, None]
            actions, next_hidden = self._choose_actions(hidden_in.astype(np.float32), learning_starts)
            new_obs, rewards, dones, infos = env.step(actions)
            check_rewards(rewards, self.n_agents, f"at agent-step {self.num_timesteps + env.num_envs}")
            self.num_timesteps += env.num_envs
            vec_steps += 1
            callback.update_locals(locals())
            if not callback.on_step():
                return RolloutReturn(vec_steps * n_copies, n_episodes, continue_training=False)

            next_obs = self._final_observations(new_obs, dones, infos)
            replay_buffer.add(
                self._last_obs, next_obs, actions, rewards, env.terminations,
                self._last_hidden, self._last_episode_starts, next_hidden, self._last_alive,
            )  # fmt: skip
            self._last_obs, self._last_hidden, self._last_alive = new_obs, next_hidden, env.alive
            self._last_episode_starts = np.asarray(dones, dtype=bool)
            self._update_current_progress_remaining(self.num_timesteps, self._total_timesteps)
            self._on_step()
            for first_slot in np.flatnonzero(dones[:: self.n_agents]) * self.n_agents:
                team = infos[first_slot]["team_episode"]
                self._team_episodes.append({"r": team["r"], "l": team["l"], "agents": team["agents"]})
                self._episode_num += 1
                n_episodes += 1
                if log_interval is not None and self._episode_num % log_interval == 0:
                    self.dump_logs()
        callback.on_rollout_end()
        return RolloutReturn(vec_steps * n_copies, n_episodes, continue_training=True)

    def _on_step(self) -> None:
        self.exploration_rate = self.exploration_schedule(self._current_progress_remaining)

    def dump_logs(self) -> None:
        """Log team returns (sum over agents and steps of an episode) and the usual time figures."""
        elapsed = max((time.time_ns() - self.start_time) / 1e9, sys.float_info.epsilon)
        if self._team_episodes:
            team_returns = [episode["r"] for episode in self._team_episodes]
            self.logger.record("rollout/ep_team_rew_mean", safe_mean(team_returns))
            # per agent: each episode's team return over the agents that lived in it (episodes restored
            # from a training state written before "agents" was counted: over every slot)
            self.logger.record(
                "rollout/ep_rew_mean",
                safe_mean(
                    [episode["r"] / episode.get("agents", self.n_agents) for episode in self._team_episodes]
                ),
            )
            self.logger.record(
                "rollout/ep_len_mean", safe_mean([episode["l"] for episode in self._team_episodes])
            )
        self.logger.record("rollout/exploration_rate", self.exploration_rate)
        self.logger.record("time/episodes", self._episode_num, exclude="tensorboard")
        self.logger.record("time/fps", int((self.num_timesteps - self._num_timesteps_at_start) / elapsed))
        self.logger.record("time/time_elapsed", int(elapsed), exclude="tensorboard")
        self.logger.record("time/total_timesteps", self.num_timesteps, exclude="tensorboard")
        self.logger.dump(step=self.num_timesteps)
