"""Fault injection on the ``ci`` budget: kill -9 of a real ``sb3-hgrn train`` during training and
during checkpoint writes, two processes on one run folder, ``--overwrite`` with a bad argument, a
resume with another config, and the bad inputs of the run-safety checks. Prints how many held.

Run: python benchmarks/fault_injection.py [--kills 4] [--seed 0]

A fault holds when no finished file is lost or damaged and the run then resumes, or is refused with
a clear message, as stated. A bad input gives a clear error when it raises the documented exception
with a message naming the problem; it goes silently wrong when nothing is raised, and crashes on any
other exception.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import pickle
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import warnings
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch as th
from stable_baselines3.common.save_util import load_from_pkl

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the tests' toy envs

from sb3_hgrn import SACHGRN, SoftHGRN, evaluate_graph_policy, make_graph_vec_env  # noqa: E402
from sb3_hgrn.cli import main  # noqa: E402
from sb3_hgrn.common.evaluation import RandomGraphPolicy  # noqa: E402
from sb3_hgrn.common.files import DamagedModelFileError, check_model_file  # noqa: E402
from tests.toy_envs import BadValueEnv, DictOnlyEnv  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
CHILD_ENV = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}


def train_args(root: Path, *extra: str) -> list[str]:
    """``train`` of Soft-HGRN on Surviving at the ``ci`` budget (6 agents, 1200 agent-steps)."""
    return ["train", "--env", "surviving_v0", "--preset", "soft_hgrn", "--budget", "ci", "--folder",
            str(root), "--verbose", "0", "--threads", "1", *extra]  # fmt: skip


def run_of(root: Path) -> Path:
    return root / "surviving_v0" / "soft_hgrn" / "seed_0"


def exit_message(args: list[str]) -> tuple[int, str]:
    """Exit status and stderr of ``sb3-hgrn ARGS`` run in this process."""
    stderr = io.StringIO()
    with contextlib.redirect_stderr(stderr), contextlib.redirect_stdout(io.StringIO()):
        try:
            status = main(args)
        except SystemExit as error:
            status = error.code
    return int(status or 0), stderr.getvalue()


def snapshot(folder: Path) -> dict[str, bytes]:
    return {str(path.relative_to(folder)): path.read_bytes() for path in folder.rglob("*") if path.is_file()}


def damaged_files(folder: Path) -> list[str]:
    """Checkpoints and replay buffers under ``folder`` that cannot be read back."""
    damaged = []
    for path in sorted(folder.rglob("[!.]*_steps.*")):  # not the temporary files of a write
        try:
            check_model_file(path) if path.suffix == ".zip" else load_from_pkl(path)
        except (DamagedModelFileError, pickle.UnpicklingError, EOFError, ValueError, OSError):
            damaged.append(path.name)
    return damaged


def start_train(root: Path, *extra: str) -> subprocess.Popen:
    command = [sys.executable, "-m", "sb3_hgrn", *train_args(root, *extra)]
    return subprocess.Popen(command, env=CHILD_ENV, stderr=subprocess.DEVNULL, stdout=subprocess.DEVNULL)


def wait_for(condition: Callable[[], bool], process: subprocess.Popen, timeout: float = 120) -> None:
    deadline = time.time() + timeout
    while not condition():
        if process.poll() is not None or time.time() > deadline:
            raise RuntimeError("the run ended before the fault was injected")
        time.sleep(0.005)


def kill(process: subprocess.Popen) -> None:
    os.kill(process.pid, signal.SIGKILL)
    process.wait()


def finishes_whole(root: Path, *extra: str) -> tuple[bool, str]:
    """Run ``train`` again in this process: it must finish the whole budget (to the next round of
    ``train_freq`` vec-steps) from a checkpoint."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the stale-lock take-over
        status, error = exit_message(train_args(root, *extra))
    results = json.loads((run_of(root) / "eval.json").read_text()) if status == 0 else {}
    held = status == 0 and results["agent_steps"] >= 1200 and results["resumed_from"] is not None
    return held, f"resumed from {results.get('resumed_from')}" if held else f"status {status}: {error[-200:]}"


# --- faults -------------------------------------------------------------------------------------
def kill_during_training(root: Path, rng: random.Random) -> tuple[bool, str]:
    extra = ("--save-freq", "120")
    process = start_train(root, *extra)
    checkpoints = run_of(root) / "checkpoints"
    wait_for(lambda: (checkpoints / "model_240_steps.zip").exists(), process)
    time.sleep(rng.uniform(0.0, 0.5))
    kill(process)
    if damaged := damaged_files(run_of(root)):
        return False, f"damaged after the kill: {damaged}"
    return finishes_whole(root, *extra)


def kill_during_checkpoint_write(root: Path, rng: random.Random) -> tuple[bool, str]:
    """Checkpoint (with the replay buffer) every collection round (``train_freq=4`` vec-steps: 50 in
    the run), so that a kill lands in a write."""
    extra = ("--save-freq", "6", "--save-replay-buffer")
    process = start_train(root, *extra)
    checkpoints = run_of(root) / "checkpoints"
    after = rng.randint(1, 40)  # checkpoints written before the kill, so that there is one to resume from

    def writing() -> bool:
        return len(list(checkpoints.glob("*.zip"))) >= after and any(checkpoints.glob(".*.tmp"))

    wait_for(writing, process)
    kill(process)
    partial = [path.name for path in checkpoints.glob(".*.tmp")]
    if damaged := damaged_files(run_of(root)):
        return False, f"damaged after the kill: {damaged}"
    held, detail = finishes_whole(root, *extra)
    left = list(checkpoints.glob(".*.tmp"))
    return held and not left, (
        f"{detail}; the kill left {', '.join(partial) or 'no partial file'}, "
        f"{'removed' if not left else 'still there'} when the run went on"
    )


def second_process_on_a_locked_folder(root: Path, rng: random.Random) -> tuple[bool, str]:
    process = start_train(root, "--save-freq", "120")
    wait_for(lambda: (run_of(root) / "checkpoints").exists(), process)
    status, error = exit_message(train_args(root, "--save-freq", "120", "--param", "gamma=0.9"))
    refused = status == 2 and f"in use by process {process.pid}" in error
    first_ok = process.wait() == 0 and (run_of(root) / "eval.json").exists()
    return refused and first_ok, f"second refused: {refused}; first run finished: {first_ok}"


def overwrite_with_a_bad_argument(root: Path, rng: random.Random) -> tuple[bool, str]:
    assert exit_message(train_args(root, "--save-freq", "600"))[0] == 0
    before = snapshot(root)
    results = [
        exit_message(train_args(root, "--overwrite", *bad))
        for bad in (["--param", "policy_kwargs.hidden_dim=-5"], ["--env-param", "n_agnts=3"])
    ]
    kept = snapshot(root) == before
    return kept and all(status == 2 for status, _ in results), f"finished run unchanged: {kept}"


def resume_with_another_config(root: Path, rng: random.Random) -> tuple[bool, str]:
    assert exit_message(train_args(root, "--save-freq", "600"))[0] == 0
    for name in ("eval.json", "model.zip"):  # killed after its last checkpoint
        (run_of(root) / name).unlink()
    before = snapshot(root)
    status, error = exit_message(train_args(root, "--save-freq", "600", "--timesteps", "1800"))
    refused = status == 2 and "total_timesteps (stored 1200, now 1800)" in error
    return refused and snapshot(root) == before, f"refused naming the key: {refused}"


FAULTS: dict[str, Callable[[Path, random.Random], tuple[bool, str]]] = {
    "kill -9 during training": kill_during_training,
    "kill -9 during a checkpoint write": kill_during_checkpoint_write,
    "second process on a locked folder": second_process_on_a_locked_folder,
    "--overwrite with a bad argument": overwrite_with_a_bad_argument,
    "resume with another config": resume_with_another_config,
}


# --- bad inputs ---------------------------------------------------------------------------------
def bad_inputs(folder: Path) -> dict[str, tuple[Callable[[], object], type[Exception], str]]:
    """Name -> (call, exception it must raise, text its message must hold)."""
    small = make_graph_vec_env("surviving_v0", seed=0, env_kwargs={"n_agents": 5, "map_size": 10})
    toy = make_graph_vec_env(DictOnlyEnv, n_envs=2)
    model = SoftHGRN("GraphPolicy", toy, batch_size=4, policy_kwargs={"hidden_dim": 16})
    observation = toy.reset()
    state = model.predict(observation)[1]
    soft, sac = folder / "soft.zip", folder / "sac.zip"
    SoftHGRN("GraphPolicy", small, batch_size=4).save(soft)
    SACHGRN("GraphPolicy", small, batch_size=4).save(sac)
    (folder / "truncated.zip").write_bytes(soft.read_bytes()[:1000])
    (folder / "garbage.zip").write_text("not a zip")
    model.save_replay_buffer(folder / "buffer.pkl")

    def algorithm(**kwargs):
        return lambda: SoftHGRN("GraphPolicy", small, **{"batch_size": 32, **kwargs})

    def learn_on(env_fn):
        return lambda: SoftHGRN("GraphPolicy", make_graph_vec_env(env_fn), batch_size=4).learn(60)

    def predict_with(key, value):
        return lambda: model.predict({**observation, key: value}, deterministic=True)

    nan_obs = observation["obs"].copy()
    nan_obs[4, 0] = np.nan
    far_obs = nan_obs.copy()
    far_obs[4, 0] = 1e6
    six_agents = make_graph_vec_env("surviving_v0", env_kwargs={"n_agents": 6, "map_size": 10})
    nan_rewards = make_graph_vec_env(lambda: DictOnlyEnv(reward=float("nan")))
    return {
        "train_freq=0": (algorithm(train_freq=0), ValueError, "train_freq must be"),
        "batch_size=abc": (algorithm(batch_size="abc"), ValueError, "batch_size must be"),
        "batch_size=-3": (algorithm(batch_size=-3), ValueError, "batch_size must be"),
        "learning_rate=abc": (algorithm(learning_rate="abc"), ValueError, "learning_rate must be"),
        "gamma=2": (algorithm(gamma=2), ValueError, "gamma must be"),
        "buffer_size=-5": (algorithm(buffer_size=-5), ValueError, "buffer_size must be"),
        "buffer_size=3": (algorithm(buffer_size=3), ValueError, "at least one batch"),
        "n_envs=2.5": (lambda: make_graph_vec_env("surviving_v0", n_envs=2.5), ValueError, "n_envs must"),
        'n_envs="2"': (lambda: make_graph_vec_env("surviving_v0", n_envs="2"), ValueError, "n_envs must"),
        "policy=None": (lambda: SoftHGRN(None, small), TypeError, "policy must be one of"),
        "NaN observation in learn": (learn_on(lambda: BadValueEnv(np.nan)), ValueError, "agent 1"),
        "inf observation in learn": (learn_on(lambda: BadValueEnv(np.inf)), ValueError, "agent 1"),
        "observation 1e6 in learn": (learn_on(lambda: BadValueEnv(1e6)), ValueError, "outside"),
        "float neighbour indices": (learn_on(lambda: BadValueEnv(offset=0.5)), ValueError, "whole number"),
        "NaN observation in predict": (predict_with("obs", nan_obs), ValueError, "agent 1 of env copy 1"),
        "observation 1e6 in predict": (predict_with("obs", far_obs), ValueError, "outside"),
        "float neighbours in predict": (
            predict_with("neighbors", observation["neighbors"] + 0.5),
            ValueError,
            "whole number",
        ),
        "NaN rewards in evaluate_graph_policy": (
            lambda: evaluate_graph_policy(RandomGraphPolicy(nan_rewards), nan_rewards, 1),
            ValueError,
            "non-finite rewards",
        ),  # fmt: skip
        "predict with an unwrapped state": (
            lambda: model.predict(observation, state=state[0]),
            ValueError,
            "state must be the tuple",
        ),
        "predict with a state of another shape": (
            lambda: model.predict(observation, state=(state[0][:, :3],)),
            ValueError,
            "expected",
        ),
        "episode_start of the wrong length": (
            lambda: model.predict(observation, state=state, episode_start=np.ones(4)),
            ValueError,
            "expected",
        ),
        "SoftHGRN.load of a SACHGRN zip": (lambda: SoftHGRN.load(sac), ValueError, "SACHGRN.load"),
        "SACHGRN.load of a SoftHGRN zip": (lambda: SACHGRN.load(soft), ValueError, "SoftHGRN.load"),
        "truncated zip": (lambda: SoftHGRN.load(folder / "truncated.zip"), ValueError, "damaged model file"),
        "not a zip": (lambda: SoftHGRN.load(folder / "garbage.zip"), ValueError, "damaged model file"),
        "replay buffer of another agent count": (
            lambda: SoftHGRN("GraphPolicy", six_agents, batch_size=4).load_replay_buffer(
                folder / "buffer.pkl"
            ),
            ValueError,
            "agents per copy",
        ),  # fmt: skip
    }


def try_input(call: Callable[[], object], expected: type[Exception], text: str) -> str:
    """``clear``, ``silent`` or ``crash``."""
    try:
        with contextlib.redirect_stdout(io.StringIO()):
            call()
    except expected as error:
        return "clear" if text in str(error) else "crash"
    except Exception:  # noqa: BLE001 - any other exception is what this probe counts
        return "crash"
    return "silent"


def run_probes(kills: int, seed: int) -> None:
    th.set_num_threads(1)
    rng = random.Random(seed)
    start = time.time()
    held = tried = 0
    print("| fault | held | detail |\n|---|---|---|")
    for name, fault in FAULTS.items():
        for _ in range(kills if name.startswith("kill") else 1):
            root = Path(tempfile.mkdtemp(prefix="faults-"))
            try:
                ok, detail = fault(root, rng)
            finally:
                shutil.rmtree(root, ignore_errors=True)
            tried, held = tried + 1, held + ok
            print(f"| {name} | {'yes' if ok else 'NO'} | {detail} |", flush=True)
    print(f"\nfaults injected: {tried}, held: {held}, data lost: {tried - held}\n")
    with tempfile.TemporaryDirectory() as folder:
        outcomes = {name: try_input(*probe) for name, probe in bad_inputs(Path(folder)).items()}
    for name, outcome in outcomes.items():
        if outcome != "clear":
            print(f"  {outcome}: {name}")
    counts = {kind: list(outcomes.values()).count(kind) for kind in ("clear", "silent", "crash")}
    print(
        f"bad inputs tried: {len(outcomes)}, clear errors: {counts['clear']}, silently wrong: "
        f"{counts['silent']}, crashed unhelpfully: {counts['crash']}\n({time.time() - start:.0f} s)"
    )


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--kills", type=int, default=3, help="repeats of each kill -9 fault")
    parser.add_argument("--seed", type=int, default=0, help="seed of the kill delays")
    args = parser.parse_args()
    run_probes(args.kills, args.seed)
