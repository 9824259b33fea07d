"""Replay buffer whose samples are whole graphs (all agents of one env copy at one step)."""

from __future__ import annotations

import math
import warnings
from typing import NamedTuple

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import BaseBuffer

from sb3_hgrn.common.soft_math import bootstrapped


class GraphSamples(NamedTuple):
    """A batch of ``batch`` graphs of ``n_agents`` agents each."""

    observations: th.Tensor  # (batch, n_agents, *obs_shape) float32
    neighbors: th.Tensor  # (batch, n_agents, max_neighbors) int64, -1 = none
    actions: th.Tensor  # (batch, n_agents) int64
    rewards: th.Tensor  # (batch, n_agents) float32, discounted sum over the sample's steps
    next_observations: th.Tensor  # (batch, n_agents, *obs_shape) float32, after the last step
    next_neighbors: th.Tensor  # (batch, n_agents, max_neighbors) int64
    terminated: th.Tensor  # (batch, n_agents) float32, 1 where the episode really ended (not time-outs)
    discounts: th.Tensor  # (batch, 1) float32, gamma ** (steps summed in rewards)
    alive: th.Tensor  # (batch, n_agents) float32, 1 where the agent lived when it acted, 0 for gone agents
    hidden: th.Tensor  # (batch, n_agents, state_dim) recurrent state fed in (zero at episode starts)
    starts: th.Tensor  # (batch,) bool, true where the observation is the first of its episode
    next_hidden: th.Tensor  # (batch, n_agents, state_dim) recurrent state produced by the last step
    groups: th.Tensor | None  # (batch, n_agents) int64 group ids (None for one group)

    def bootstrapped(self, next_value: th.Tensor) -> th.Tensor:
        """The regression target ``rewards + discounts * (1 - terminated) * next_value`` ``(batch,
        n_agents)`` from the state values ``(batch, n_agents)`` of the next observations."""
        return bootstrapped(self.rewards, self.discounts, self.terminated, next_value)


def smallest_index_dtype(n_agents: int) -> np.dtype:
    """Smallest signed integer dtype holding agent indices ``-1 .. n_agents - 1``."""
    for dtype in (np.int8, np.int16, np.int32):
        if n_agents - 1 <= np.iinfo(dtype).max:
            return np.dtype(dtype)
    return np.dtype(np.int64)


def available_memory() -> int | None:
    """Bytes of memory available to new allocations (psutil's ``virtual_memory().available`` where
    psutil is installed, else Linux's ``MemAvailable``), or None if unknown."""
    try:
        import psutil
    except ImportError:
        pass
    else:
        return int(psutil.virtual_memory().available)
    try:
        with open("/proc/meminfo") as meminfo:
            for line in meminfo:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        return None
    return None


MEMORY_WARNING_FRACTION = 0.5
"""A replay buffer expected to take more than this fraction of the available memory is warned about."""
MEMORY_WARNING_BYTES = 2 * 2**30
"""A replay buffer expected to take more than this is warned about however much memory is available:
a laptop's share for one run (SB3's default of 1,000,000 transitions of image-like views passes it)."""


def warn_if_too_large(expected_bytes: int, buffer_size: int) -> None:
    """Warn (``UserWarning``) when a replay buffer of ``buffer_size`` agent-transitions is expected to
    take ``expected_bytes`` once full, more than :data:`MEMORY_WARNING_BYTES` or more than
    :data:`MEMORY_WARNING_FRACTION` of the available memory, whichever is less; the warning states the
    bytes and a ``buffer_size`` that would stay under that limit."""
    available = available_memory()
    share = None if available is None else int(MEMORY_WARNING_FRACTION * available)
    limit = MEMORY_WARNING_BYTES if share is None else min(MEMORY_WARNING_BYTES, share)
    if expected_bytes <= limit:
        return
    of_available = share is not None and share <= limit
    where = f" of the {available / 2**30:.1f} GiB of memory available" if of_available else ""
    fitting = int(buffer_size * limit / expected_bytes)
    warnings.warn(
        f"The replay buffer of buffer_size={buffer_size} agent-transitions will take "
        f"{expected_bytes} bytes ({expected_bytes / 2**30:.2f} GiB) once full, more than "
        f"{limit / 2**30:.2f} GiB{where}; lower buffer_size (buffer_size={fitting} would take about "
        f"{limit / 2**30:.2f} GiB) or store smaller observations.",
        UserWarning,
        stacklevel=3,
    )


class GraphReplayBuffer(BaseBuffer):
    """Replay buffer of joint transitions, stored per env copy and sampled as whole graphs.

    ``buffer_size`` counts agent-transitions, as in SB3 (``num_timesteps`` counts agent-steps):
    the buffer keeps ``buffer_size // n_envs`` steps of all ``n_envs = n_copies * n_agents`` slots.
    A sample draws (step, copy) pairs, so ``batch_size`` counts graphs.

    Memory is kept small: observations keep the env's own dtype (int8 for Surviving) and shape (any
    ``obs_shape``; the learner's networks flatten or encode them), neighbour
    indices use the smallest integer type for the agent count, the recurrent state is stored once
    per step (by default in float16): row ``t`` holds the state carried into step ``t`` and a flag
    marking episode starts, and the state produced by step ``t`` is the one carried into ``t + 1``.
    With agent groups (an observation key ``group``) the group ids are stored as int8; an agent's
    group never changes, so they serve the next observations too. Every transition records whether
    its agent was alive when it acted: the rows of agents that died or left before the step are
    kept (a graph keeps all its slots) but sampled with ``alive = 0``, for the losses to leave out.

    With ``n_steps > 1`` a sample is an n-step transition (as SB3's ``NStepReplayBuffer``): its
    rewards are the ``gamma``-discounted sum over up to ``n_steps`` consecutive steps of its copy and
    its next observation and state those after the last of them, with ``discounts = gamma ** k`` for
    the ``k`` steps summed. A sample stops early at the end of its episode (a termination or a time
    limit), at the newest stored step, after a step where any agent of its copy terminated, and
    before a step where the set of living agents changed, so every agent of a graph sums the same
    steps and bootstraps from the same observation. The entropy terms of the soft value at the
    skipped states are left out of the sum.

    :param buffer_size: capacity in agent-transitions.
    :param observation_space: the graph VecEnv's Dict space (keys ``obs`` and ``neighbors``).
    :param action_space: ``Discrete`` action space.
    :param device: torch device of the sampled tensors.
    :param n_envs: number of VecEnv slots (``n_copies * n_agents``).
    :param n_agents: agents per env copy.
    :param state_dim: width of the recurrent state (0 without recurrence).
    :param hidden_dtype: storage dtype of the recurrent state.
    :param n_steps: steps summed per sample (1: one-step transitions).
    :param gamma: discount of the summed rewards and of the bootstrap.

    The bytes the buffer will hold once full (:meth:`expected_nbytes`, from :meth:`storage_layout`)
    are checked before its arrays are made: above half of the available memory (2 GiB where that is
    unknown) a ``UserWarning`` states them and a ``buffer_size`` that would fit.
    """

    observations: np.ndarray  # (steps, n_copies, n_agents, *obs_shape), the env's dtype
    next_observations: np.ndarray  # as observations
    neighbors: np.ndarray  # (steps, n_copies, n_agents, max_neighbors), the smallest index dtype
    next_neighbors: np.ndarray  # as neighbors
    actions: np.ndarray  # (steps, n_copies, n_agents) uint8 (int64 above 256 actions)
    rewards: np.ndarray  # (steps, n_copies, n_agents) float32
    terminated: np.ndarray  # (steps, n_copies, n_agents) bool
    alive: np.ndarray  # (steps, n_copies, n_agents) bool
    hidden: np.ndarray  # (steps, n_copies, n_agents, state_dim) hidden_dtype
    episode_starts: np.ndarray  # (steps, n_copies) bool
    groups: np.ndarray | None  # (steps, n_copies, n_agents) int8 with agent groups, else None

    def __init__(
        self,
        buffer_size: int,
        observation_space: spaces.Dict,
        action_space: spaces.Discrete,
        device: th.device | str = "auto",
        n_envs: int = 1,
        n_agents: int = 1,
        state_dim: int = 0,
        hidden_dtype: np.dtype | str = np.float16,
        n_steps: int = 1,
        gamma: float = 0.99,
    ):
        super().__init__(buffer_size, observation_space, action_space, device, n_envs=n_envs)
        if n_envs % n_agents != 0:
            raise ValueError(f"n_envs={n_envs} is not a multiple of n_agents={n_agents}.")
        self.n_steps = n_steps
        self.gamma = gamma
        self.n_agents = n_agents
        self.n_copies = n_envs // n_agents
        layout = self.storage_layout(
            buffer_size, observation_space, action_space, n_envs, n_agents, state_dim, hidden_dtype
        )
        warn_if_too_large(self.layout_nbytes(layout), buffer_size)
        self.buffer_size = self.steps_held(buffer_size, n_envs)
        self.groups = None
        # np.zeros maps untouched pages lazily (zeros_like would write every byte up front)
        for name, (shape, dtype) in layout.items():
            setattr(self, name, np.zeros(shape, dtype=dtype))

    @staticmethod
    def steps_held(buffer_size: int, n_envs: int) -> int:
        """Steps of all ``n_envs`` slots that ``buffer_size`` agent-transitions hold (at least 2)."""
        return max(buffer_size // n_envs, 2)

    @staticmethod
    def storage_layout(
        buffer_size: int,
        observation_space: spaces.Dict,
        action_space: spaces.Discrete,
        n_envs: int = 1,
        n_agents: int = 1,
        state_dim: int = 0,
        hidden_dtype: np.dtype | str = np.float16,
    ) -> dict[str, tuple[tuple[int, ...], np.dtype]]:
        """Shape and dtype of every storage array of a buffer built with these arguments: rows of
        ``(steps, n_copies, n_agents)`` with ``steps = max(buffer_size // n_envs, 2)``, the
        observations and next observations ``(*rows, *obs_shape)`` in the env's dtype, the neighbour
        lists ``(*rows, max_neighbors)`` in the smallest index dtype, actions (uint8 up to 256
        actions, else int64), rewards float32, terminations and who was alive bool, the recurrent
        state ``(*rows, state_dim)`` in ``hidden_dtype``, episode starts ``(steps, n_copies)`` and,
        with agent groups, the group ids int8."""
        rows = (GraphReplayBuffer.steps_held(buffer_size, n_envs), n_envs // n_agents, n_agents)
        obs_space = observation_space["obs"]
        index_dtype = smallest_index_dtype(n_agents)
        neighbors = (*rows, observation_space["neighbors"].shape[0])
        observations = (*rows, *obs_space.shape)
        layout = {
            "observations": (observations, np.dtype(obs_space.dtype)),
            "next_observations": (observations, np.dtype(obs_space.dtype)),
            "neighbors": (neighbors, index_dtype),
            "next_neighbors": (neighbors, index_dtype),
            "actions": (rows, np.dtype(np.uint8 if action_space.n <= 256 else np.int64)),
            "rewards": (rows, np.dtype(np.float32)),
            "terminated": (rows, np.dtype(bool)),
            "alive": (rows, np.dtype(bool)),
            "hidden": ((*rows, state_dim), np.dtype(hidden_dtype)),
            "episode_starts": (rows[:2], np.dtype(bool)),
        }
        if "group" in observation_space.spaces:
            layout["groups"] = (rows, np.dtype(np.int8))
        return layout

    @staticmethod
    def layout_nbytes(layout: dict[str, tuple[tuple[int, ...], np.dtype]]) -> int:
        """Bytes of the arrays of a :meth:`storage_layout`."""
        return sum(int(np.prod(shape)) * dtype.itemsize for shape, dtype in layout.values())

    @classmethod
    def expected_nbytes(
        cls,
        buffer_size: int,
        observation_space: spaces.Dict,
        action_space: spaces.Discrete,
        n_envs: int = 1,
        n_agents: int = 1,
        state_dim: int = 0,
        hidden_dtype: np.dtype | str = np.float16,
    ) -> int:
        """Bytes a buffer built with these arguments holds (its :attr:`nbytes`), without building it."""
        return cls.layout_nbytes(
            cls.storage_layout(
                buffer_size, observation_space, action_space, n_envs, n_agents, state_dim, hidden_dtype
            )
        )

    @property
    def nbytes(self) -> int:
        """Bytes held by all storage arrays."""
        arrays = (
            self.observations, self.next_observations, self.neighbors, self.next_neighbors,
            self.actions, self.rewards, self.terminated, self.alive, self.hidden, self.episode_starts,
            self.groups,
        )  # fmt: skip
        return sum(array.nbytes for array in arrays if array is not None)

    def add(
        self,
        obs: dict[str, np.ndarray],
        next_obs: dict[str, np.ndarray],
        actions: np.ndarray,
        rewards: np.ndarray,
        terminated: np.ndarray,
        hidden: np.ndarray,
        episode_starts: np.ndarray,
        next_hidden: np.ndarray,
        alive: np.ndarray | None = None,
    ) -> None:
        """Store one step of all slots.

        :param obs: ``{"obs": (n_envs, *obs_shape), "neighbors": (n_envs, max_neighbors)}``.
        :param next_obs: the same for the next step (the final observation where an episode ended).
        :param actions: ``(n_envs,)``.
        :param rewards: ``(n_envs,)``.
        :param terminated: ``(n_envs,)`` bool, true episode ends only (not time limits).
        :param hidden: ``(n_envs, state_dim)`` state carried into this step, before the reset at
            episode starts.
        :param episode_starts: ``(n_envs,)`` bool, ``obs`` is the first of an episode.
        :param next_hidden: ``(n_envs, state_dim)`` state produced by this step.
        :param alive: ``(n_envs,)`` bool, the agents alive in ``obs`` (``None``: all), those whose
            transitions count; an agent dying at this step is alive in ``obs`` (and ``terminated``).
        """
        shape = (self.n_copies, self.n_agents)
        obs_shape = self.observations.shape[3:]
        pos = self.pos
        self.observations[pos] = obs["obs"].reshape(*shape, *obs_shape)
        self.next_observations[pos] = next_obs["obs"].reshape(*shape, *obs_shape)
        self.neighbors[pos] = obs["neighbors"].reshape(*shape, -1)
        self.next_neighbors[pos] = next_obs["neighbors"].reshape(*shape, -1)
        self.actions[pos] = actions.reshape(shape)
        self.rewards[pos] = rewards.reshape(shape)
        self.terminated[pos] = terminated.reshape(shape)
        self.alive[pos] = True if alive is None else alive.reshape(shape)
        self.hidden[pos] = hidden.reshape(*shape, -1)
        self.episode_starts[pos] = episode_starts.reshape(shape)[:, 0]
        if self.groups is not None:
            self.groups[pos] = obs["group"].reshape(shape)
        self.pos = (pos + 1) % self.buffer_size
        # the produced state is the one carried into the next step: it lands in the next row
        self.hidden[self.pos] = next_hidden.reshape(*shape, -1)
        if self.pos == 0:
            self.full = True

    def __setstate__(self, state: dict) -> None:
        """Restore a pickled buffer; one saved before transitions recorded who was alive has every
        agent alive, as its env could not lose agents."""
        self.__dict__.update(state)
        if "alive" not in state:
            self.alive = np.ones(self.rewards.shape, dtype=bool)
        self.__dict__.setdefault("n_steps", 1)
        self.__dict__.setdefault("gamma", 0.99)

    def return_rms(self, gamma: float) -> float:
        """Root mean square of the ``gamma``-discounted returns of the stored transitions of living
        agents, summed within each episode over the stored steps in time order (a return still open
        at the newest step counts the steps stored so far); 0.0 for an empty buffer."""
        stored = self.buffer_size if self.full else self.pos
        if stored == 0:
            return 0.0
        order = (np.arange(stored) + (self.pos if self.full else 0)) % self.buffer_size
        rewards, alive = self.rewards[order], self.alive[order]
        continues = ~self.episode_starts[order][1:, :, None]  # step t + 1 belongs to t's episode
        returns = np.zeros_like(rewards[0], dtype=np.float64)
        total, count = 0.0, 0
        for step in range(stored - 1, -1, -1):
            following = returns * continues[step] if step < stored - 1 else returns
            returns = rewards[step] + gamma * following
            total += float(np.square(returns[alive[step]]).sum())
            count += int(alive[step].sum())
        return math.sqrt(total / count) if count else 0.0

    def sample(self, batch_size: int, env=None) -> GraphSamples:
        """Draw ``batch_size`` graphs uniformly from the stored steps and copies."""
        return self.sample_sequences(batch_size, 1)[0]

    def sample_sequences(self, n_sequences: int, length: int) -> list[GraphSamples]:
        """Draw ``n_sequences`` runs of ``length`` consecutive stored steps, each of one copy, uniformly
        over their first step: item ``k`` of the list holds the ``k``-th step of every run
        (``n_sequences`` graphs), each an (n-step) sample as :meth:`sample` gives. A run may cross
        episode ends; its samples' ``starts`` flag where the recurrent state restarts from zero."""
        stored = self.buffer_size - 1 if self.full else self.pos
        if stored == 0:
            raise RuntimeError("Cannot sample from an empty replay buffer.")
        if stored < length:
            raise RuntimeError(
                f"Cannot sample runs of {length} steps from a replay buffer holding {stored} step(s)."
            )
        # a full buffer's row `pos` holds the oldest step, but its state slot the newest next state
        oldest = (self.pos + 1) % self.buffer_size if self.full else 0
        rows = (oldest + np.random.randint(0, stored - length + 1, size=n_sequences)) % self.buffer_size
        copies = np.random.randint(0, self.n_copies, size=n_sequences)
        return [self._get_samples((rows + k) % self.buffer_size, copies) for k in range(length)]

    def _last_steps(self, rows: np.ndarray, copies: np.ndarray) -> np.ndarray:
        """Offset ``(batch,)`` from each sample's first row to the last row it sums (0 .. n_steps - 1)."""
        offsets = np.arange(1, self.n_steps)
        later_rows = (rows[:, None] + offsets) % self.buffer_size  # (batch, n_steps - 1)
        earlier_rows = (later_rows - 1) % self.buffer_size
        first_alive = self.alive[rows, copies][:, None]  # (batch, 1, n_agents)
        copies = copies[:, None]
        stored_after = (self.pos - 1 - rows) % self.buffer_size  # rows stored after the first
        continues = (
            (offsets <= stored_after[:, None])
            & ~self.episode_starts[later_rows, copies]
            & ~self.terminated[earlier_rows, copies].any(axis=-1)
            & (self.alive[later_rows, copies] == first_alive).all(axis=-1)
        )  # (batch, n_steps - 1): the step at that offset belongs to the sample if all before it do
        return np.cumprod(continues, axis=1).sum(axis=1)

    def _get_samples(self, rows: np.ndarray, copies: np.ndarray, env=None) -> GraphSamples:
        last = self._last_steps(rows, copies)
        window = np.arange(self.n_steps)
        window_rows = (rows[:, None] + window) % self.buffer_size  # (batch, n_steps)
        weights = (self.gamma**window * (window <= last[:, None])).astype(np.float32)
        rewards = np.einsum("bk,bka->ba", weights, self.rewards[window_rows, copies[:, None]])
        last_rows = (rows + last) % self.buffer_size
        next_rows = (last_rows + 1) % self.buffer_size
        starts = self.episode_starts[rows, copies]
        keep = ~starts
        hidden = self.hidden[rows, copies] * keep[:, None, None].astype(self.hidden.dtype)
        device = self.device

        def floats(array: np.ndarray) -> th.Tensor:
            return th.as_tensor(array, device=device).float()

        def longs(array: np.ndarray) -> th.Tensor:
            return th.as_tensor(array, device=device).long()

        return GraphSamples(
            observations=floats(self.observations[rows, copies]),
            neighbors=longs(self.neighbors[rows, copies]),
            actions=longs(self.actions[rows, copies]),
            rewards=floats(rewards),
            next_observations=floats(self.next_observations[last_rows, copies]),
            next_neighbors=longs(self.next_neighbors[last_rows, copies]),
            terminated=floats(self.terminated[last_rows, copies]),
            discounts=floats(self.gamma ** (last[:, None] + 1.0)),
            alive=floats(self.alive[rows, copies]),
            hidden=floats(hidden),
            starts=th.as_tensor(starts, device=device),
            next_hidden=floats(self.hidden[next_rows, copies]),
            groups=None if self.groups is None else longs(self.groups[rows, copies]),
        )
