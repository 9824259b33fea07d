import re
import sys
import warnings
from types import SimpleNamespace

import gymnasium as gym
import numpy as np
import pytest
import torch as th

from sb3_hgrn.common import buffers
from sb3_hgrn.common.attention import GraphBatch
from sb3_hgrn.common.buffers import GraphReplayBuffer, smallest_index_dtype
from sb3_hgrn.common.off_policy import concatenated, unroll

N_AGENTS, N_COPIES, STATE = 3, 2, 4


def make_buffer(steps: int = 5, **kwargs) -> GraphReplayBuffer:
    obs_space = gym.spaces.Dict(
        {
            "obs": gym.spaces.Box(-1, 10, shape=(2,), dtype=np.int8),
            "neighbors": gym.spaces.Box(-1, 2**31 - 1, shape=(2,), dtype=np.int32),
        }
    )
    n_envs = N_AGENTS * N_COPIES
    return GraphReplayBuffer(
        steps * n_envs, obs_space, gym.spaces.Discrete(5), device="cpu",
        n_envs=n_envs, n_agents=N_AGENTS, state_dim=STATE, hidden_dtype="float32", **kwargs,
    )  # fmt: skip


def step_data(t: int) -> dict:
    """Slot values encode (step, slot) so samples can be traced back."""
    n_envs = N_AGENTS * N_COPIES
    slots = np.arange(n_envs)
    obs = {"obs": np.stack([np.full(n_envs, t), slots], 1).astype(np.int8),
           "neighbors": np.stack([slots % N_AGENTS, np.full(n_envs, -1)], 1).astype(np.int32)}  # fmt: skip
    return dict(
        obs=obs,
        next_obs={"obs": obs["obs"] + np.array([100, 0], dtype=np.int8), "neighbors": obs["neighbors"]},
        actions=slots % 5,
        rewards=(10 * t + slots).astype(np.float32),
        terminated=np.zeros(n_envs, dtype=bool),
        hidden=np.full((n_envs, STATE), t, dtype=np.float32),
        episode_starts=np.full(n_envs, t == 2),
        next_hidden=np.full((n_envs, STATE), t + 1, dtype=np.float32),
    )


def test_samples_are_whole_graphs_with_matching_fields():
    buffer = make_buffer()
    for t in range(4):
        buffer.add(**step_data(t))
    batch = buffer.sample(64)
    assert batch.observations.shape == (64, N_AGENTS, 2)
    assert batch.neighbors.shape == (64, N_AGENTS, 2) and batch.hidden.shape == (64, N_AGENTS, STATE)
    steps = batch.observations[:, 0, 0]
    slots = batch.observations[:, :, 1]
    # one graph = consecutive slots of one copy, all from the same step
    assert ((slots - slots[:, :1]) == np.arange(N_AGENTS)).all()
    assert (slots[:, 0] % N_AGENTS == 0).all()
    assert (batch.observations[:, :, 0] == steps[:, None]).all()
    np.testing.assert_array_equal(batch.rewards, 10 * steps[:, None] + slots)
    np.testing.assert_array_equal(
        batch.next_observations[:, :, 0], (steps[:, None] + 100).expand(-1, N_AGENTS)
    )
    np.testing.assert_array_equal(batch.neighbors[:, :, 1], -1)
    # state fed in: zero at the episode start (step 2), else the stored one; state out: step + 1
    expected_in = th.where(steps == 2, 0.0, steps)
    np.testing.assert_array_equal(batch.hidden[:, :, 0], expected_in[:, None].expand(-1, N_AGENTS))
    np.testing.assert_array_equal(batch.next_hidden[:, :, 0], (steps + 1)[:, None].expand(-1, N_AGENTS))
    assert set(steps.tolist()) == {0.0, 1.0, 2.0, 3.0}


def test_full_buffer_never_samples_the_overwritten_row():
    buffer = make_buffer(steps=5)
    for t in range(7):  # wraps: rows hold steps 5, 6, 2, 3, 4; row 2 (pos) is excluded
        buffer.add(**step_data(t))
    assert buffer.full and buffer.pos == 2
    steps = set(buffer.sample(400).observations[:, 0, 0].tolist())
    assert steps == {3.0, 4.0, 5.0, 6.0}
    batch = buffer.sample(400)
    np.testing.assert_array_equal(batch.next_hidden[:, 0, 0], batch.observations[:, 0, 0] + 1)


def test_runs_are_consecutive_steps_of_one_copy_and_flag_episode_starts():
    """Runs of 3 steps from a wrapped buffer (rows hold steps 5, 6, 2, 3, 4, row 2 overwritten): they
    start at steps 3 or 4 only, keep their copy, and flag the episode start of step 2 (none here)."""
    buffer = make_buffer(steps=5)
    for t in range(7):
        buffer.add(**step_data(t))
    steps = buffer.sample_sequences(300, 3)
    assert len(steps) == 3 and steps[0].observations.shape[0] == 300
    first = steps[0].observations[:, 0, 0]
    assert set(first.tolist()) == {3.0, 4.0}
    for k, step in enumerate(steps):
        np.testing.assert_array_equal(step.observations[:, 0, 0], first + k)
        np.testing.assert_array_equal(step.observations[:, :, 1], steps[0].observations[:, :, 1])
        assert not step.starts.any()
    with pytest.raises(RuntimeError, match="runs of 5 steps from a replay buffer holding 4"):
        buffer.sample_sequences(1, 5)

    fresh = make_buffer(steps=8)
    for t in range(5):  # step 2 starts an episode
        fresh.add(**step_data(t))
    for step in fresh.sample_sequences(200, 2):
        np.testing.assert_array_equal(step.starts.numpy(), step.observations[:, 0, 0].numpy() == 2)


def test_unroll_carries_the_state_along_a_run_and_restarts_it_at_episode_starts():
    """A network whose state counts its steps: along a run of 4 steps from the stored state 10 it
    reads 10, 11, 12, 13; a run whose third step starts an episode reads 10, 11, 0, 1. Outputs and
    samples are step-major."""
    buffer = make_buffer(steps=8)
    for t in range(6):
        buffer.add(**step_data(t))
    steps = [buffer._get_samples(np.array([0, 0]) + k, np.array([0, 1])) for k in range(4)]
    steps = [step._replace(starts=th.tensor([False, k == 2])) for k, step in enumerate(steps)]

    class Counter:
        """Stands in for a network whose memory counts its steps; its output is the state it read."""

        gru = "a memory"

        def features(self, observations, graph):
            return observations

        def remember(self, features, state, groups):
            return state + 1

        def outputs(self, memories, graph):
            return memories - 1

    first = th.full((2, N_AGENTS, 1), 10.0)
    batch = concatenated(steps)
    starts = [step.starts for step in steps]
    outputs = unroll(Counter(), batch.observations, GraphBatch(batch.neighbors), first, starts)
    np.testing.assert_array_equal(outputs[:, 0, 0].numpy(), [10, 10, 11, 11, 12, 0, 13, 1])
    np.testing.assert_array_equal(batch.observations[:, 0, 0].numpy(), [0, 0, 1, 1, 2, 2, 3, 3])
    assert concatenated(steps[:1]) is steps[0]


def test_n_step_samples_sum_their_copys_steps_up_to_episode_ends():
    """Steps 0-7, an episode starting at step 3, agent 0 of copy 0 terminating at step 5, agent 2 of
    copy 1 joining at step 5, rewards 2 ** t: with n = 3 and gamma 0.5 every sample sums up to three
    steps of its own episode, stopping after a termination in its copy and before a change of who is
    alive."""
    buffer = make_buffer(steps=10, n_steps=3, gamma=0.5)
    for t in range(8):
        data = step_data(t)
        data["rewards"] = np.full(N_AGENTS * N_COPIES, 2.0**t, dtype=np.float32)
        data["episode_starts"] = np.full(N_AGENTS * N_COPIES, t == 3)
        data["terminated"][0] = t == 5
        data["alive"] = np.ones(N_AGENTS * N_COPIES, dtype=bool)
        data["alive"][2 * N_AGENTS - 1] = t >= 5
        buffer.add(**data)
    rows = np.tile(np.arange(8), 2)
    copies = np.repeat(np.arange(2), 8)
    batch = buffer._get_samples(rows, copies)
    # last step summed per first step: episode 0-2 ends at 2; copy 0 stops after its termination at
    # 5, copy 1 before agent 2 joins at 5
    last = np.array([[2, 2, 2, 5, 5, 5, 7, 7], [2, 2, 2, 4, 4, 7, 7, 7]]).reshape(-1)
    expected = [
        sum(0.5 ** (k - t) * 2.0**k for k in range(t, end + 1)) for t, end in zip(rows, last, strict=True)
    ]
    np.testing.assert_allclose(batch.rewards, np.repeat(np.array(expected)[:, None], N_AGENTS, 1))
    np.testing.assert_allclose(batch.discounts[:, 0], 0.5 ** (last - rows + 1.0))
    np.testing.assert_array_equal(batch.next_observations[:, 0, 0], last + 100)
    np.testing.assert_array_equal(batch.next_hidden[:, 0, 0], last + 1)
    terminated = np.zeros((16, N_AGENTS))
    terminated[3:6, 0] = 1  # copy 0's samples that end at step 5
    np.testing.assert_array_equal(batch.terminated, terminated)
    np.testing.assert_array_equal(batch.observations[:, 0, 0], rows)


def test_n_step_samples_of_a_full_buffer_stop_at_the_newest_step():
    """Rows hold steps 5, 6, 2, 3, 4 of one episode after wrapping: a sample from step 5 sums steps
    5 and 6 only, one from step 6 that step alone, never the oldest step stored after them."""
    buffer = make_buffer(steps=5, n_steps=3, gamma=0.5)
    for t in range(7):
        buffer.add(**{**step_data(t), "episode_starts": np.zeros(N_AGENTS * N_COPIES, dtype=bool)})
    batch = buffer._get_samples(np.array([0, 1, 3]), np.zeros(3, dtype=int))  # steps 5, 6, 3
    np.testing.assert_array_equal(batch.next_observations[:, 0, 0], [106, 106, 105])
    np.testing.assert_allclose(batch.discounts[:, 0], [0.25, 0.5, 0.125])
    np.testing.assert_allclose(batch.rewards[:, 0], [50 + 0.5 * 60, 60, 30 + 0.5 * 40 + 0.25 * 50])


def test_one_step_samples_bootstrap_with_gamma():
    buffer = make_buffer(gamma=0.9)
    for t in range(3):
        buffer.add(**step_data(t))
    batch = buffer.sample(16)
    np.testing.assert_allclose(batch.discounts, np.full((16, 1), 0.9, dtype=np.float32))
    next_value = th.ones(16, N_AGENTS)
    np.testing.assert_allclose(batch.bootstrapped(next_value), batch.rewards + 0.9, rtol=1e-6)


def test_compact_storage_dtypes():
    buffer = make_buffer()
    assert buffer.observations.dtype == np.int8
    assert buffer.neighbors.dtype == np.int8 and buffer.actions.dtype == np.uint8
    assert smallest_index_dtype(128) == np.int8 and smallest_index_dtype(129) == np.int16
    assert smallest_index_dtype(1000) == np.int16
    assert buffer.nbytes > 0


def test_expected_bytes_count_the_full_buffer_without_allocating_it():
    buffer = make_buffer(steps=5)
    arguments = (buffer.observation_space, buffer.action_space, N_AGENTS * N_COPIES, N_AGENTS, STATE)
    # per agent-transition: obs and next obs 2 x 2 int8, neighbours 2 x 2 int8, action 1, reward 4,
    # terminated 1, alive 1, state 4 float32; and one episode-start flag per copy and step
    assert GraphReplayBuffer.expected_nbytes(5 * 6, *arguments, "float32") == 5 * 6 * 31 + 5 * 2
    assert GraphReplayBuffer.expected_nbytes(5 * 6, *arguments, "float32") == buffer.nbytes
    grouped = gym.spaces.Dict({**buffer.observation_space.spaces, "group": gym.spaces.Discrete(2)})
    assert GraphReplayBuffer.expected_nbytes(5 * 6, grouped, *arguments[1:], "float32") == buffer.nbytes + 30
    huge = GraphReplayBuffer.expected_nbytes(10**12, *arguments)  # a terabyte, never allocated
    assert huge == 10**12 // 6 * 6 * (31 - 8) + 10**12 // 6 * 2  # the state in float16


def test_empty_buffer_and_bad_slot_count():
    with pytest.raises(RuntimeError, match="empty"):
        make_buffer().sample(4)
    with pytest.raises(ValueError, match="multiple"):
        GraphReplayBuffer(100, make_buffer().observation_space, gym.spaces.Discrete(2), n_envs=5, n_agents=3)


def test_warns_when_the_full_buffer_would_not_fit_in_memory():
    from sb3_hgrn.common.buffers import available_memory

    available = available_memory()
    if available is None:
        pytest.skip("no /proc/meminfo on this system")
    space = gym.spaces.Dict(
        {
            "obs": gym.spaces.Box(0.0, 1.0, shape=(1024,)),
            "neighbors": gym.spaces.Box(-1, 10, shape=(4,), dtype=np.int32),
        }
    )
    rows_needed = available // (2 * 1024 * 4 * 2) + 8  # obs and next obs of 2 agents, float32
    with pytest.warns(UserWarning, match="lower buffer_size"):
        GraphReplayBuffer(
            int(rows_needed * 2), space, gym.spaces.Discrete(3), device="cpu", n_envs=2, n_agents=2
        )


def view_space(view: tuple[int, ...], dtype=np.float32, groups: bool = False) -> gym.spaces.Dict:
    """A graph VecEnv's observation space with image-like views of shape ``view``."""
    spaces = {
        "obs": gym.spaces.Box(0, 1, shape=view, dtype=dtype),
        "neighbors": gym.spaces.Box(-1, 2**31 - 1, shape=(5,), dtype=np.int32),
    }
    if groups:
        spaces["group"] = gym.spaces.Box(0, 1, shape=(), dtype=np.int8)
    return gym.spaces.Dict(spaces)


@pytest.mark.parametrize(
    "space, n_actions, n_agents, hidden_dtype",
    [
        (view_space((9, 9, 5)), 5, 3, "float16"),
        (view_space((2,), np.int8, groups=True), 7, 3, "float32"),
        (view_space((3, 4), np.uint8), 300, 130, "float16"),  # int64 actions, int16 neighbour indices
    ],
)
def test_expected_bytes_are_the_bytes_the_buffer_holds(space, n_actions, n_agents, hidden_dtype):
    for buffer_size, n_copies in [(40 * n_agents, 2), (1, 1)]:  # also the 2-step minimum
        arguments = (buffer_size, space, gym.spaces.Discrete(n_actions), n_copies * n_agents, n_agents, 6)
        buffer = GraphReplayBuffer(*arguments[:3], "cpu", *arguments[3:], hidden_dtype=hidden_dtype)
        assert GraphReplayBuffer.expected_nbytes(*arguments, hidden_dtype=hidden_dtype) == buffer.nbytes


@pytest.mark.parametrize(
    "available_gib, limit_text, limit_gib",
    [
        (64, "more than 2.00 GiB; lower", 2.0),  # a large machine: still over a laptop's share
        (6, "more than 2.00 GiB; lower", 2.0),
        (3, "more than 1.50 GiB of the 3.0 GiB of memory available; lower", 1.5),
    ],
)
def test_warns_with_the_expected_bytes_before_allocating(monkeypatch, available_gib, limit_text, limit_gib):
    """The 1M default on 9x9x5 float32 views (3.15 GiB once full) is warned about however much memory
    is available, before any array is made, with a buffer_size that stays under 2 GiB or half the
    available memory, whichever is less."""
    monkeypatch.setattr(buffers, "available_memory", lambda: available_gib * 2**30)
    space, actions = view_space((9, 9, 5)), gym.spaces.Discrete(5)
    expected = GraphReplayBuffer.expected_nbytes(1_000_000, space, actions, 20, 20, 64)
    assert 3 * 2**30 < expected < 4 * 2**30

    def no_allocation(*args, **kwargs):
        raise AssertionError("an array was made before the warning")

    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)
        with monkeypatch.context() as patch, pytest.raises(UserWarning) as warned:
            patch.setattr(buffers.np, "zeros", no_allocation)
            GraphReplayBuffer(1_000_000, space, actions, "cpu", n_envs=20, n_agents=20, state_dim=64)
        message = str(warned.value)
        assert f"buffer_size=1000000 agent-transitions will take {expected} bytes" in message
        assert limit_text in message
        fitting = int(re.search(r"\(buffer_size=(\d+) would", message).group(1))
        fitting_bytes = GraphReplayBuffer.expected_nbytes(fitting, space, actions, 20, 20, 64)
        assert (limit_gib - 0.01) * 2**30 < fitting_bytes <= limit_gib * 2**30
        buffers.warn_if_too_large(fitting_bytes, fitting)  # no warning: it would raise here


def test_memory_limit_comes_from_psutil_else_a_fixed_size(monkeypatch):
    monkeypatch.setitem(
        sys.modules, "psutil", SimpleNamespace(virtual_memory=lambda: SimpleNamespace(available=6))
    )
    assert buffers.available_memory() == 6
    monkeypatch.setattr(buffers, "available_memory", lambda: None)
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)
        buffers.warn_if_too_large(2 * 2**30, 10)
    with pytest.warns(UserWarning, match="more than 2.00 GiB; lower buffer_size"):
        buffers.warn_if_too_large(2 * 2**30 + 1, 10)


def test_return_rms_sums_each_episode_of_the_living_agents_in_time_order():
    """Rewards 2 ** t, gamma 0.5: an episode of steps 0-1 (returns 2, 2) and one of steps 2-4 (12,
    16, 16), one slot gone at steps 0-1; then a wrapped buffer holding steps 2-5 of one episode."""
    buffer = make_buffer(steps=10, gamma=0.5)
    for t in range(5):
        data = step_data(t)
        data["rewards"] = np.full(N_AGENTS * N_COPIES, 2.0**t, dtype=np.float32)
        data["alive"] = np.ones(N_AGENTS * N_COPIES, dtype=bool)
        data["alive"][-1] = t >= 2
        buffer.add(**data)
    expected = (5 * 4 + 5 * 4 + 6 * 144 + 6 * 256 + 6 * 256) / 28
    assert buffer.return_rms(0.5) == pytest.approx(np.sqrt(expected))
    wrapped = make_buffer(steps=4, gamma=0.5)
    assert wrapped.return_rms(0.5) == 0.0
    for t in range(6):
        data = step_data(t)
        data["rewards"] = np.full(N_AGENTS * N_COPIES, 2.0**t, dtype=np.float32)
        data["episode_starts"] = np.full(N_AGENTS * N_COPIES, t == 0)
        wrapped.add(**data)
    assert wrapped.full and wrapped.pos == 2  # rows hold steps 4, 5, 2, 3
    assert wrapped.return_rms(0.5) == pytest.approx(np.sqrt((16**2 + 24**2 + 32**2 + 32**2) / 4))
