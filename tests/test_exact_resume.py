"""A killed run resumed from a checkpoint with its replay buffer goes on bit for bit as the same run
uninterrupted: the env copies' state round trip, the training state beside every checkpoint, and a
real ``sb3-hgrn train`` killed with SIGKILL and resumed."""

import json
import os
import pickle
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from stable_baselines3.common.save_util import load_from_pkl

from sb3_hgrn import SoftHGRN, make_graph_vec_env
from sb3_hgrn.cli import main
from sb3_hgrn.common.vec_env import UnpicklableEnvError
from sb3_hgrn.experiments.callbacks import AtomicCheckpointCallback

REPO = Path(__file__).resolve().parents[1]
HYPERPARAMS = REPO / "sb3_hgrn" / "hyperparams"

N_AGENTS, EPISODE = 5, 20  # Surviving's ci episodes: 20 env steps
TOTAL, SAVE_FREQ, RESUMED_AT = 700, 50, 360  # agent-steps
TRAIN = [
    "train", "--env", "surviving_v0", "--preset", "soft_hgrn", "--budget", "ci", "--verbose", "0",
    "--threads", "1", "--timesteps", str(TOTAL), "--save-freq", str(SAVE_FREQ), "--save-replay-buffer",
    "--param", "batch_size=4", "policy_kwargs.hidden_dim=16", "--env-param", f"n_agents={N_AGENTS}",
    "--keep-checkpoints", "0",
]  # fmt: skip


def ci_env(name: str, n_envs: int, seed: int):
    """``n_envs`` copies of ``name`` at its ci size."""
    kwargs = yaml.safe_load((HYPERPARAMS / f"{name}.yml").read_text())["budgets"]["ci"]["env_kwargs"]
    return make_graph_vec_env(name, n_envs=n_envs, seed=seed, env_kwargs=kwargs)


def shared_arrays(env) -> set[tuple[str, str]]:
    """The pairs of an env copy's array attributes that share memory (views of one another)."""
    arrays = {name: value for name, value in vars(env).items() if isinstance(value, np.ndarray)}
    names = sorted(arrays)
    pairs = [(a, b) for i, a in enumerate(names) for b in names[i + 1 :]]
    return {(a, b) for a, b in pairs if np.shares_memory(arrays[a], arrays[b])}


def steps(env, actions: np.ndarray) -> list:
    """Everything ``env`` returns for each row of ``actions`` ``(n_steps, num_envs)``."""
    results = []
    for row in actions:
        obs, rewards, dones, infos = env.step(row)
        team = [info["team_episode"]["r"] for info in infos if "team_episode" in info]
        results.append((obs["obs"].copy(), obs["neighbors"].copy(), rewards, dones, team))
    return results


@pytest.mark.parametrize("name", ["surviving_v0", "uav_mbs_v0", "ctc_v0"])
def test_a_vec_env_restored_from_its_state_steps_on_as_the_original(name):
    """Two copies stepped into their second episodes, saved, then stepped on (over episode ends):
    a VecEnv of another seed restored from the state returns the same, views included."""
    env = ci_env(name, 2, seed=0)
    mask = env.reset().get("action_mask")
    n_actions = env.action_space.n if mask is None else mask.sum(axis=1)  # per slot
    rng = np.random.default_rng(0)
    steps(env, rng.integers(0, n_actions, size=(27, env.num_envs)))  # 20-step episodes: mid-episode
    state = env.get_state()
    actions = rng.integers(0, n_actions, size=(30, env.num_envs))
    expected = steps(env, actions)
    restored = ci_env(name, 2, seed=1)
    restored.reset()
    restored.set_state(state)
    assert [shared_arrays(copy) for copy in restored.envs] == [shared_arrays(copy) for copy in env.envs]
    for got, want in zip(steps(restored, actions), expected, strict=True):
        for got_part, want_part in zip(got, want, strict=True):
            np.testing.assert_array_equal(got_part, want_part)


def test_an_env_state_of_another_layout_is_refused():
    state = ci_env("surviving_v0", 2, seed=0).get_state()
    with pytest.raises(ValueError, match="holds 2 copies of 6 agents, this VecEnv 1 of 6"):
        ci_env("surviving_v0", 1, seed=0).set_state(state)


def test_an_env_that_cannot_be_pickled_is_named():
    env = ci_env("pursuit_v0", 1, seed=0)
    with pytest.raises(UnpicklableEnvError, match="The state of PursuitEnv cannot be pickled"):
        env.get_state()


def test_checkpoints_of_an_unpicklable_env_warn_once_and_hold_no_training_state(tmp_path):
    env = ci_env("surviving_v0", 1, seed=0)
    env.envs[0].lock = threading.Lock()  # an attribute pickle refuses
    model = SoftHGRN("GraphPolicy", env, batch_size=4, learning_starts=10_000, train_freq=4, seed=0)
    save_freq = 8  # vec-steps, two rounds of train_freq
    callback = AtomicCheckpointCallback(save_freq, str(tmp_path), name_prefix="model")
    with pytest.warns(UserWarning, match="hold no training state") as warned:
        model.learn(3 * save_freq * env.num_envs, callback=callback)
    assert len([w for w in warned if "training state" in str(w.message)]) == 1
    expected = {f"model_{k * save_freq * env.num_envs}_steps.zip" for k in (1, 2, 3)}
    assert {path.name for path in tmp_path.iterdir()} == expected


def run_of(root: Path) -> Path:
    return root / "surviving_v0" / "soft_hgrn" / "seed_0"


def checkpoint_steps(path: Path) -> int:
    """The agent-steps in a checkpoint file's name (``..._<steps>_steps.<ext>``)."""
    return int(path.name.rsplit("_", 2)[-2])


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory) -> Path:
    """The run folder of the test run, trained without a break."""
    root = tmp_path_factory.mktemp("uninterrupted")
    assert main([*TRAIN, "--folder", str(root)]) == 0
    return run_of(root)


def team_returns(folder: Path) -> list[str]:
    """The ``r,l`` of every row of ``team_returns.csv`` (``t`` is wall time)."""
    rows = (folder / "team_returns.csv").read_text().splitlines()[2:]
    return [row.rsplit(",", 1)[0] for row in rows]


def kill_and_rewind(root: Path, steps: int, killed_at: int) -> None:
    """Run the test run in a subprocess and SIGKILL it once it has a checkpoint at ``killed_at``
    agent-steps or later; then keep the checkpoints up to ``steps`` only, as if the kill came right
    after that one (``team_returns.csv`` keeps the episodes that ended after it)."""
    checkpoints = run_of(root) / "checkpoints"
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    process = subprocess.Popen([sys.executable, "-m", "sb3_hgrn", *TRAIN, "--folder", str(root)], env=env)
    try:
        deadline = time.time() + 60
        while max(map(checkpoint_steps, checkpoints.glob("model_*_steps.zip")), default=0) < killed_at:
            assert process.poll() is None and time.time() < deadline, "the run ended before its kill"
            time.sleep(0.01)
    finally:
        os.kill(process.pid, signal.SIGKILL)
        process.wait()
    assert not (run_of(root) / "eval.json").exists()
    for path in checkpoints.iterdir():
        if checkpoint_steps(path) > steps:
            path.unlink()


def test_a_killed_run_resumed_with_its_replay_buffer_is_bit_identical(uninterrupted, tmp_path):
    """Killed after an episode end and resumed from a checkpoint before it, in the middle of an
    episode (and due in the middle of a collection round): the final model, replay buffer, team
    returns and evaluation equal the uninterrupted run's."""
    assert (RESUMED_AT // N_AGENTS) % EPISODE != 0  # the envs are mid-episode at the checkpoint
    kill_and_rewind(tmp_path, RESUMED_AT, killed_at=RESUMED_AT + EPISODE * N_AGENTS)
    assert len(team_returns(run_of(tmp_path))) > RESUMED_AT // N_AGENTS // EPISODE  # rows to drop
    with pytest.warns(UserWarning, match="Taking over the lock"):
        assert main([*TRAIN, "--folder", str(tmp_path)]) == 0
    resumed = run_of(tmp_path)
    results = json.loads((resumed / "eval.json").read_text())
    assert results["resumed_from"] == f"model_{RESUMED_AT}_steps.zip"
    want, got = (SoftHGRN.load(folder / "model.zip") for folder in (uninterrupted, resumed))
    assert want.num_timesteps == got.num_timesteps == TOTAL
    for name, tensor in want.policy.state_dict().items():
        assert torch.equal(got.policy.state_dict()[name], tensor), name
    for name, state in want.policy.optimizer.state_dict()["state"].items():
        for key, value in state.items():
            assert torch.equal(got.policy.optimizer.state_dict()["state"][name][key], value), key
    buffer_file = f"checkpoints/model_replay_buffer_{TOTAL}_steps.pkl"
    want_buffer, got_buffer = (load_from_pkl(folder / buffer_file) for folder in (uninterrupted, resumed))
    assert got_buffer.pos == want_buffer.pos > 0
    for name in ("observations", "next_observations", "neighbors", "actions", "rewards", "hidden"):
        np.testing.assert_array_equal(getattr(got_buffer, name), getattr(want_buffer, name), err_msg=name)
    assert team_returns(resumed) == team_returns(uninterrupted)
    assert len(team_returns(resumed)) == TOTAL // N_AGENTS // EPISODE
    want_eval = json.loads((uninterrupted / "eval.json").read_text())
    for key in ("returns", "lengths", "action_frequencies", "epsilon_evaluations"):
        assert results[key] == want_eval[key], key


def test_checkpoints_are_written_at_the_end_of_their_collection_round(uninterrupted):
    """Every ``--save-freq`` agent-steps a checkpoint falls due; it is written when its round of
    ``train_freq`` vec-steps has been collected and trained on, named after the agent-steps then."""
    train_freq = yaml.safe_load((HYPERPARAMS / "surviving_v0.yml").read_text())["budgets"]["ci"]["default"][
        "train_freq"
    ]
    round_steps = train_freq * N_AGENTS
    due = range(SAVE_FREQ, TOTAL + 1, SAVE_FREQ)
    expected = sorted({-(-steps // round_steps) * round_steps for steps in due})
    checkpoints = uninterrupted / "checkpoints"
    assert sorted(checkpoint_steps(path) for path in checkpoints.glob("model_*_steps.zip")) == expected
    for steps in expected:
        with open(checkpoints / f"model_training_state_{steps}_steps.pkl", "rb") as file:
            state = pickle.load(file)
        assert state["num_timesteps"] == steps
        buffer = load_from_pkl(checkpoints / f"model_replay_buffer_{steps}_steps.pkl")
        assert buffer.pos == steps // N_AGENTS  # every vec-step up to the checkpoint is stored


def test_resume_skips_a_damaged_training_state(uninterrupted, tmp_path):
    folder = run_of(tmp_path)
    shutil.copytree(uninterrupted, folder)
    for name in ("eval.json", "model.zip"):  # killed after its last checkpoint
        (folder / name).unlink()
    state = folder / "checkpoints" / f"model_training_state_{TOTAL}_steps.pkl"
    state.write_bytes(state.read_bytes()[: state.stat().st_size // 2])
    with pytest.warns(UserWarning, match=f"Skipping the training state .*{state.name}"):
        assert main([*TRAIN, "--folder", str(tmp_path)]) == 0
    assert json.loads((folder / "eval.json").read_text())["resumed_from"] == f"model_{TOTAL}_steps.zip"
