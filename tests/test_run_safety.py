"""Run folders never lose work: validation before any change, refused resumes, moved-aside runs,
atomic writes, damaged checkpoints skipped, a real ``sb3-hgrn train`` killed with SIGKILL, and one
process per run folder; algorithm arguments checked at construction."""

import copy
import io
import json
import os
import shutil
import signal
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import gymnasium
import numpy as np
import pytest
import torch as th
import yaml
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.save_util import load_from_pkl, save_to_pkl

from sb3_hgrn import SACHGRN, SoftHGRN, evaluate_graph_policy, make_graph_vec_env
from sb3_hgrn.cli import main
from sb3_hgrn.common import saved_controllers
from sb3_hgrn.common.checks import MAX_ABS_REWARD, observation_problem
from sb3_hgrn.common.evaluation import RandomGraphPolicy
from sb3_hgrn.common.files import DamagedModelFileError, save_model_atomically, write_text_atomically
from sb3_hgrn.common.hgrn import HGRN
from sb3_hgrn.common.off_policy import GraphOffPolicyAlgorithm
from sb3_hgrn.experiments.callbacks import (
    AtomicCheckpointCallback,
    remove_old_checkpoints,
    rewind_team_returns,
)
from sb3_hgrn.experiments.config import ConfigError, RunConfig, resolve_config
from sb3_hgrn.experiments.jobs import LOG_FILE, Job, check_budget_of_folder, run_jobs
from sb3_hgrn.experiments.lock import PID_FILE, RunLock
from sb3_hgrn.experiments.runs import trained_parameter_count
from sb3_hgrn.experiments.trust import check_stored_model_paths
from sb3_hgrn.sac_hgrn.policies import SACHGRNPolicy
from tests.toy_envs import BadValueEnv, DictOnlyEnv

REPO = Path(__file__).resolve().parents[1]

TOY = ["--budget", "ci", "--verbose", "0", "--threads", "1"]
SMALL = ["--param", "batch_size=4", "policy_kwargs.hidden_dim=16", "--env-param", "n_agents=5"]


def train_args(root: Path, timesteps: int = 200, *extra: str) -> list[str]:
    """``train`` of a tiny Soft-HGRN run on Surviving (5 agents, 20-step episodes) under ``root``."""
    args = ["train", "--env", "surviving_v0", "--preset", "soft_hgrn", "--folder", str(root), *TOY]
    return [*args, "--timesteps", str(timesteps), "--save-freq", "100", *SMALL, *extra]


def run_of(root: Path) -> Path:
    return root / "surviving_v0" / "soft_hgrn" / "seed_0"


def snapshot(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` by relative path, with its bytes."""
    return {str(path.relative_to(folder)): path.read_bytes() for path in folder.rglob("*") if path.is_file()}


@pytest.fixture(scope="module")
def finished_root(tmp_path_factory) -> Path:
    """The root of a finished tiny run (200 agent-steps, checkpoints at 100 and 200)."""
    root = tmp_path_factory.mktemp("finished")
    assert main(train_args(root)) == 0
    return root


@pytest.fixture
def root(finished_root, tmp_path) -> Path:
    """A copy of the finished run's root that a test may change."""
    shutil.copytree(finished_root, tmp_path / "runs")
    return tmp_path / "runs"


def fails_with(args: list[str], capsys) -> str:
    """The error message of a command that must exit with status 2."""
    with pytest.raises(SystemExit) as error:
        main(args)
    assert error.value.code == 2
    return capsys.readouterr().err


@pytest.mark.parametrize(
    "bad, message",
    [
        (["--param", "policy_kwargs.hidden_dim=-5"], "hidden_dim must be positive"),
        (["--env-param", "n_agnts=3"], "Cannot build surviving_v0"),
    ],
)
def test_overwrite_with_a_bad_argument_keeps_the_finished_run(root, bad, message, capsys):
    before = snapshot(root)
    assert message in fails_with([*train_args(root), "--overwrite", *bad], capsys)
    assert snapshot(root) == before


def test_resume_with_another_config_is_refused_naming_the_keys(root, capsys):
    folder = run_of(root)
    for name in ("eval.json", "model.zip"):  # a run killed after its last checkpoint
        (folder / name).unlink()
    before = snapshot(root)
    error = fails_with(train_args(root, 300), capsys)
    assert "another configuration" in error and "total_timesteps (stored 200, now 300)" in error
    error = fails_with([*train_args(root), "--env-param", "n_agents=6"], capsys)
    assert "env_kwargs.n_agents (stored 5, now 6)" in error and "total_timesteps" not in error
    error = fails_with([*train_args(root), "--param", "gamma=0.9"], capsys)
    assert "hyperparams.gamma (stored missing, now 0.9)" in error
    assert snapshot(root) == before


def test_overwrite_moves_the_old_run_aside_and_keeps_it(root, monkeypatch):
    folder = run_of(root)
    old_eval = (folder / "eval.json").read_bytes()

    def killed(*args, **kwargs):
        raise KeyboardInterrupt

    with monkeypatch.context() as patch:
        patch.setattr(GraphOffPolicyAlgorithm, "learn", killed)
        with pytest.raises(KeyboardInterrupt):
            main([*train_args(root), "--overwrite"])
    (aside,) = folder.parent.glob("seed_0.replaced-*")
    assert (aside / "eval.json").read_bytes() == old_eval and (aside / "checkpoints").is_dir()
    assert not (folder / "eval.json").exists()

    assert main([*train_args(root), "--overwrite"]) == 0
    assert (folder / "eval.json").exists() and (folder / "model.zip").exists()
    asides = sorted(folder.parent.glob("seed_0.replaced-*"))
    assert len(asides) == 2 and aside in asides  # the killed attempt was moved aside too; both stay
    assert (aside / "eval.json").read_bytes() == old_eval and (aside / "model.zip").is_file()


def test_the_budget_check_reads_run_folders_not_runs_moved_aside(tmp_path):
    def complete(name: str, budget: str) -> None:
        folder = tmp_path / "surviving_v0" / "soft_hgrn" / name
        folder.mkdir(parents=True)
        (folder / "eval.json").write_text(json.dumps({"completed": True, "budget": budget}))

    complete("seed_0", "ci")
    complete("seed_0.replaced-20261201T161500Z", "cpu")
    check_budget_of_folder(tmp_path, "ci")
    complete("seed_1", "cpu")
    with pytest.raises(ConfigError, match="seed_1 holds a run of budget 'cpu', not 'ci'"):
        check_budget_of_folder(tmp_path, "ci")


def test_rewind_team_returns_keeps_the_episodes_of_the_checkpoint(tmp_path):
    path = tmp_path / "team_returns.csv"
    header = '#{"t_start": 0, "env_id": "x", "n_agents": 5, "n_copies": 1}\nr,l,t\n'
    path.write_text(header + "1.0,20,0.1\n2.0,20,0.2\n3.0,20,0.3\n4.0,2")  # the last row cut short
    assert rewind_team_returns(path, 2) == 2
    assert path.read_text() == header + "1.0,20,0.1\n2.0,20,0.2\n"
    path.write_text(header + "1.0,20,0.1\n2.0,2")
    assert rewind_team_returns(path, 5) == 1 and path.read_text() == header + "1.0,20,0.1\n"
    assert rewind_team_returns(path, 5) == 0 and rewind_team_returns(tmp_path / "missing.csv", 0) == 0


def cut_short(path: Path) -> None:
    """Keep the first half of a file, as a process killed while writing it would."""
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


def as_killed(folder: Path) -> None:
    """Make ``folder`` look like a run killed after its last checkpoint."""
    for name in ("eval.json", "model.zip"):
        (folder / name).unlink()


def test_resume_skips_a_damaged_checkpoint(root, capsys):
    folder = run_of(root)
    as_killed(folder)
    cut_short(folder / "checkpoints" / "model_200_steps.zip")
    leftover = folder / "checkpoints" / ".model_300_steps.zip.4242.tmp"  # of a write killed midway
    leftover.write_bytes(b"PK")
    users_file = folder / ".notes.tmp"  # a hidden file of the user's, not of an atomic write
    users_file.write_text("keep")
    with pytest.warns(UserWarning, match="Skipping damaged model file .*model_200_steps.zip"):
        assert main(train_args(root)) == 0
    assert not leftover.exists()
    assert users_file.read_text() == "keep"
    results = json.loads((folder / "eval.json").read_text())
    assert results["resumed_from"] == "model_100_steps.zip" and results["agent_steps"] == 200


def test_a_damaged_checkpoint_is_renamed_aside_not_written_over(root):
    folder = run_of(root)
    as_killed(folder)
    damaged = folder / "checkpoints" / "model_200_steps.zip"
    cut_short(damaged)
    damaged_bytes = damaged.read_bytes()
    with pytest.warns(UserWarning, match="Renamed the damaged model file .*model_200_steps.zip"):
        assert main(train_args(root)) == 0
    (aside,) = (folder / "checkpoints").glob("model_200_steps.damaged-*.zip")
    assert aside.read_bytes() == damaged_bytes
    assert SoftHGRN.load(damaged).num_timesteps == 200  # the resumed run's own checkpoint


def never_learns(*args, **kwargs):
    raise AssertionError("a finished model was trained again")


@pytest.mark.parametrize("checkpoints", [False, True])
def test_a_run_killed_during_its_final_evaluation_is_evaluated_not_retrained(root, monkeypatch, checkpoints):
    folder = run_of(root)
    (folder / "eval.json").unlink()
    if not checkpoints:
        shutil.rmtree(folder / "checkpoints")
    before = snapshot(folder / "checkpoints") if checkpoints else {}
    model_bytes = (folder / "model.zip").read_bytes()
    monkeypatch.setattr(GraphOffPolicyAlgorithm, "learn", never_learns)
    assert main(train_args(root)) == 0
    assert (folder / "model.zip").read_bytes() == model_bytes
    results = json.loads((folder / "eval.json").read_text())
    assert results["completed"] and results["resumed_from"] == "model.zip" and results["agent_steps"] == 200
    assert (snapshot(folder / "checkpoints") if checkpoints else {}) == before


def test_a_damaged_final_model_is_renamed_aside_and_the_run_resumed(root):
    folder = run_of(root)
    (folder / "eval.json").unlink()
    cut_short(folder / "model.zip")
    damaged_bytes = (folder / "model.zip").read_bytes()
    with pytest.warns(UserWarning, match="Renamed the damaged model file .*model.zip"):
        assert main(train_args(root)) == 0
    (aside,) = folder.glob("model.damaged-*.zip")
    assert aside.read_bytes() == damaged_bytes
    assert json.loads((folder / "eval.json").read_text())["resumed_from"] == "model_200_steps.zip"
    assert SoftHGRN.load(folder / "model.zip").num_timesteps == 200


def test_evaluate_skips_a_damaged_checkpoint_and_names_a_damaged_file(root, capsys):
    folder = run_of(root)
    as_killed(folder)
    newest = folder / "checkpoints" / "model_200_steps.zip"
    cut_short(newest)
    with pytest.warns(UserWarning, match="model_200_steps.zip"):
        assert main(["evaluate", str(folder), "--episodes", "1", "--threads", "1"]) == 0
    assert "over 1 episodes" in capsys.readouterr().out
    assert f"damaged model file {newest}" in fails_with(["evaluate", str(newest)], capsys)


def test_load_of_a_damaged_zip_names_the_file(finished_root, tmp_path):
    model = run_of(finished_root) / "model.zip"
    truncated, garbage, bad_data = tmp_path / "truncated.zip", tmp_path / "garbage.zip", tmp_path / "data.zip"
    truncated.write_bytes(model.read_bytes()[:1000])
    garbage.write_text("not a zip")
    with zipfile.ZipFile(model) as source, zipfile.ZipFile(bad_data, "w") as target:
        for name in source.namelist():
            target.writestr(name, b"{not json" if name == "data" else source.read(name))
    for path in (truncated, garbage, bad_data):
        with pytest.raises(DamagedModelFileError, match=f"damaged model file {path}"):
            SoftHGRN.load(path)
    with pytest.raises(ValueError, match="damaged model file .*truncated.zip"):
        SoftHGRN.load(tmp_path / "truncated")  # SB3 adds the .zip


class Interrupted(Exception):
    """Stands in for a kill while a file is written."""


def half_save(model, path) -> None:
    """Write half of ``model``'s zip to ``path`` (a file name or a file), then fail."""
    buffer = io.BytesIO()
    BaseAlgorithm.save(model, buffer)
    half = buffer.getvalue()[: len(buffer.getvalue()) // 2]
    if hasattr(path, "write"):
        path.write(half)
    else:
        Path(path).write_bytes(half)
    raise Interrupted


class CutShort:
    """A model whose ``save`` writes half of the real zip, then fails."""

    def __init__(self, model):
        self.model = model

    def save(self, path) -> None:
        half_save(self.model, path)


def test_a_save_cut_short_leaves_the_old_file_and_no_partial_one(finished_root, tmp_path):
    model = SoftHGRN.load(run_of(finished_root) / "model.zip")
    target = tmp_path / "model.zip"
    save_model_atomically(model, target)
    before = target.read_bytes()
    with pytest.raises(Interrupted):
        save_model_atomically(CutShort(model), target)
    assert target.read_bytes() == before and os.listdir(tmp_path) == ["model.zip"]


def test_an_atomic_write_flushes_the_file_then_its_folder_after_the_rename(tmp_path, monkeypatch):
    events = []
    fsync, replace = os.fsync, os.replace

    def recorded_fsync(descriptor):
        flushed = os.fstat(descriptor)
        events.append("fsync folder" if os.path.samestat(flushed, os.stat(tmp_path)) else "fsync file")
        fsync(descriptor)

    def recorded_replace(source, target):
        events.append("replace")
        replace(source, target)

    monkeypatch.setattr(os, "fsync", recorded_fsync)
    monkeypatch.setattr(os, "replace", recorded_replace)
    write_text_atomically(tmp_path / "eval.json", "{}")
    assert events == ["fsync file", "replace", "fsync folder"]
    assert (tmp_path / "eval.json").read_text() == "{}"


def checkpoint_files(folder: Path, steps: list[int], kinds=("", "replay_buffer_", "training_state_")) -> set:
    """The names of the checkpoint files of ``steps`` agent-steps (zip and companions)."""
    return {f"model_{kind}{step}_steps.{'zip' if not kind else 'pkl'}" for step in steps for kind in kinds}


def test_old_checkpoints_are_removed_zip_first_keeping_the_newest(tmp_path, monkeypatch):
    for name in checkpoint_files(tmp_path, [100, 200, 300, 400, 500]) | {"model_replay_buffer_50_steps.pkl"}:
        (tmp_path / name).write_bytes(b"x")
    others = {"model_200_steps.damaged-20261201T161500Z.zip", "notes.txt", ".model_100_steps.zip.7.tmp"}
    for name in others:
        (tmp_path / name).write_bytes(b"x")
    unlinked = []
    unlink = Path.unlink
    monkeypatch.setattr(
        Path, "unlink", lambda path, **kwargs: unlinked.append(path.name) or unlink(path, **kwargs)
    )
    # 400 was just written; 500 is newer (of an earlier attempt): kept, as are 400 and one older one.
    assert remove_old_checkpoints(tmp_path, "model", 400, keep=2) == [200, 100, 50]
    assert {path.name for path in tmp_path.iterdir()} == checkpoint_files(tmp_path, [300, 400, 500]) | others
    for step in (200, 100):
        assert unlinked.index(f"model_{step}_steps.zip") < unlinked.index(
            f"model_replay_buffer_{step}_steps.pkl"
        )
        assert unlinked.index(f"model_{step}_steps.zip") < unlinked.index(
            f"model_training_state_{step}_steps.pkl"
        )
    assert remove_old_checkpoints(tmp_path, "model", 500, keep=3) == []


def test_train_keeps_the_newest_checkpoints_and_their_replay_buffers(tmp_path):
    args = [*train_args(tmp_path, 500), "--save-replay-buffer", "--keep-checkpoints", "2"]
    assert main(args) == 0
    folder = run_of(tmp_path)
    assert {path.name for path in (folder / "checkpoints").iterdir()} == checkpoint_files(folder, [400, 500])
    assert SoftHGRN.load(folder / "model.zip").num_timesteps == 500
    # Resuming with another count is the same run; 0 keeps every checkpoint.
    as_killed(folder)
    assert main([*train_args(tmp_path, 500), "--keep-checkpoints", "0"]) == 0
    assert yaml.safe_load((folder / "config.yml").read_text())["keep_checkpoints"] == 0


def test_keep_checkpoints_comes_from_the_budget_and_bad_counts_are_refused(tmp_path, capsys):
    config = tmp_path / "keep.yml"
    config.write_text("budgets: {ci: {keep_checkpoints: 1}}\n")
    assert resolve_config("surviving_v0", "soft_hgrn", "ci", config_file=config).keep_checkpoints == 1
    assert resolve_config("surviving_v0", "soft_hgrn", "ci").keep_checkpoints == 3
    assert (
        resolve_config(
            "surviving_v0", "soft_hgrn", "ci", config_file=config, keep_checkpoints=0
        ).keep_checkpoints
        == 0
    )
    config.write_text("budgets: {ci: {keep_checkpoints: -1}}\n")
    error = fails_with([*train_args(tmp_path), "--config", str(config)], capsys)
    assert "budget ci: keep_checkpoints must be a whole number >= 0" in error and "-1" in error
    error = fails_with([*train_args(tmp_path), "--keep-checkpoints", "-2"], capsys)
    assert "--keep-checkpoints must be a whole number >= 0" in error
    with pytest.raises(ValueError, match="keep must be a whole number >= 0"):
        AtomicCheckpointCallback(10, str(tmp_path), keep=-1)


def test_a_kill_while_saving_a_checkpoint_leaves_the_earlier_ones_whole(root, monkeypatch, capsys):
    folder = run_of(root)
    saves = []

    def second_save_cut_short(self, path, *args, **kwargs):
        saves.append(path)
        if len(saves) == 2:
            half_save(self, path)
        BaseAlgorithm.save(self, path, *args, **kwargs)

    monkeypatch.setattr(SoftHGRN, "save", second_save_cut_short)
    with pytest.raises(Interrupted):
        main([*train_args(root), "--overwrite"])
    assert sorted(path.name for path in (folder / "checkpoints").glob("*.zip")) == ["model_100_steps.zip"]
    assert not list((folder / "checkpoints").glob(".*"))  # no partial file
    monkeypatch.undo()
    assert main(train_args(root)) == 0
    assert json.loads((folder / "eval.json").read_text())["resumed_from"] == "model_100_steps.zip"


def test_sigkill_during_training_then_resume(tmp_path):
    """A real ``sb3-hgrn train`` killed with SIGKILL once it has checkpoints resumes from the newest."""
    folder = run_of(tmp_path)
    args = train_args(tmp_path, 1500)
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    process = subprocess.Popen([sys.executable, "-m", "sb3_hgrn", *args], env=env)
    try:
        deadline = time.time() + 60
        while not (folder / "checkpoints" / "model_300_steps.zip").exists():
            assert process.poll() is None and time.time() < deadline, "the run ended before its kill"
            time.sleep(0.02)
    finally:
        os.kill(process.pid, signal.SIGKILL)
        process.wait()
    assert not (folder / "eval.json").exists()
    rows = (folder / "team_returns.csv").read_text().splitlines()[2:]
    with pytest.warns(UserWarning, match=f"Taking over the lock .* from process {process.pid}"):
        assert main(args) == 0
    results = json.loads((folder / "eval.json").read_text())
    assert results["agent_steps"] == 1500 and results["resumed_from"].startswith("model_")
    steps = int(results["resumed_from"].split("_")[1])
    assert steps >= 300 and len(rows) >= steps // 100
    rows = (folder / "team_returns.csv").read_text().splitlines()[2:]
    assert len(rows) == 15 and all(len(row.split(",")) == 3 for row in rows)  # one row per episode


HOLD = """
import sys, time
from sb3_hgrn.experiments.lock import RunLock
with RunLock(sys.argv[1]):
    print("locked", flush=True)
    time.sleep(120)
"""


@pytest.fixture
def holder(tmp_path):
    """A second process holding the lock of the run folder under ``tmp_path``."""
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    command = [sys.executable, "-c", HOLD, str(run_of(tmp_path))]
    process = subprocess.Popen(command, stdout=subprocess.PIPE, text=True, env=env)
    assert process.stdout.readline() == "locked\n"
    yield process
    process.kill()
    process.wait()


def test_a_second_process_on_a_locked_folder_is_refused_naming_the_pid(tmp_path, holder, capsys):
    error = fails_with(train_args(tmp_path), capsys)
    assert f"is in use by process {holder.pid}" in error
    assert sorted(os.listdir(run_of(tmp_path))) == [".lock", PID_FILE]  # nothing of a run written


def test_a_stale_lock_of_a_killed_process_is_taken_over(tmp_path, holder):
    holder.send_signal(signal.SIGKILL)
    holder.wait()
    assert (run_of(tmp_path) / PID_FILE).read_text() == f"{holder.pid}\n"  # left behind by the kill
    with pytest.warns(UserWarning, match=f"from process {holder.pid}, which ended without releasing it"):
        assert main(train_args(tmp_path)) == 0
    assert (run_of(tmp_path) / "eval.json").exists() and not (run_of(tmp_path) / PID_FILE).exists()


def test_sweeps_skip_a_locked_run_and_keep_its_log(tmp_path):
    job = Job("surviving_v0", "soft_hgrn", 0, run_of(tmp_path))
    job.folder.mkdir(parents=True)
    (job.folder / LOG_FILE).write_text("the running run's log\n")
    messages = []
    with RunLock(job.folder):
        failed = run_jobs([job], lambda job: ["--help"], log=messages.append)
    assert failed == [job] and f"in use by process {os.getpid()}" in messages[0]
    assert (job.folder / LOG_FILE).read_text() == "the running run's log\n"


@pytest.fixture(scope="module")
def small_env():
    env = make_graph_vec_env("surviving_v0", seed=0, env_kwargs={"n_agents": 5, "map_size": 10})
    yield env
    env.close()


def numel(*modules: th.nn.Module) -> int:
    return sum(param.numel() for module in modules for param in module.parameters())


def test_n_parameters_counts_the_trained_weights_only(small_env, finished_root):
    soft = SoftHGRN("GraphPolicy", small_env, policy_kwargs=dict(hidden_dim=16, average_tau=0.1), seed=0)
    assert trained_parameter_count(soft) == numel(soft.policy.q_net) < numel(soft.policy)
    sac = SACHGRN("GraphPolicy", small_env, policy_kwargs=dict(hidden_dim=16, n_critics=2), seed=0)
    assert trained_parameter_count(sac) == numel(sac.policy.actor, sac.policy.critics) < numel(sac.policy)
    stored = yaml.safe_load((run_of(finished_root) / "config.yml").read_text())["extra"]["n_parameters"]
    assert stored == numel(SoftHGRN.load(run_of(finished_root) / "model.zip").policy.q_net)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"train_freq": 0}, "train_freq must be an integer >= 1"),
        ({"train_freq": (0, "episode")}, "train_freq must be an integer >= 1"),
        ({"batch_size": "abc"}, "batch_size must be a positive integer"),
        ({"batch_size": -3}, "batch_size must be a positive integer"),
        ({"batch_size": 2.5}, "batch_size must be a positive integer"),
        ({"gamma": 2}, r"gamma must be a number in \[0, 1\], got 2"),
        ({"gamma": -0.1}, r"gamma must be a number in \[0, 1\]"),
        ({"n_steps": 0}, "n_steps must be a positive integer .*, got 0"),
        ({"n_steps": 2.0}, "n_steps must be a positive integer"),
        ({"buffer_size": -5}, "buffer_size must be a positive integer"),
        (
            {"buffer_size": 3},
            r"buffer_size must hold at least one batch of graphs: .* = 160 agent-transitions, got 3",
        ),
        ({"learning_rate": "abc"}, "learning_rate must be a positive number or a schedule"),
        ({"learning_rate": -1e-3}, "learning_rate must be a positive number or a schedule"),
    ],
)
@pytest.mark.parametrize("algorithm", [SoftHGRN, SACHGRN])
def test_bad_algorithm_arguments_raise_naming_the_argument(algorithm, small_env, kwargs, message):
    with pytest.raises(ValueError, match=message):
        algorithm("GraphPolicy", small_env, **{"batch_size": 32, **kwargs})


ANY_POLICY = r"\w+HGRNPolicy"
WRONG_TYPES = [
    ({"hidden_dtype": "float8"}, r"hidden_dtype must name a numpy float dtype .*, got 'float8'"),
    ({"hidden_dtype": "int8"}, r"hidden_dtype must name a numpy float dtype .*, got 'int8'"),
    ({"learning_starts": "abc"}, "learning_starts must be an integer, got 'abc'"),
    ({"learning_starts": 1e3}, "learning_starts must be an integer, got 1000.0"),
    ({"tau": "1"}, "tau must be a number, got '1'"),
    ({"learn_alpha": "no"}, "learn_alpha must be true or false, got 'no'"),
    ({"exploration_final_eps": "x"}, "exploration_final_eps must be a number or None, got 'x'"),
    (
        {"policy_kwargs": {"hidden_dtype": "float16"}},
        f"policy_kwargs.hidden_dtype is not an argument of {ANY_POLICY}; .* hidden_dtype is an argument "
        r"of \w+HGRN itself",
    ),
    ({"policy_kwargs": {"hidden_dim": "abc"}}, "policy_kwargs.hidden_dim must be an integer, got 'abc'"),
    ({"policy_kwargs": {"hidden_dim": 32.0}}, "policy_kwargs.hidden_dim must be an integer, got 32.0"),
    ({"policy_kwargs": {"n_heads": "2"}}, "policy_kwargs.n_heads must be an integer, got '2'"),
    ({"policy_kwargs": {"head_dim": 1.5}}, "policy_kwargs.head_dim must be an integer or None, got 1.5"),
    ({"policy_kwargs": {"recurrent": "no"}}, "policy_kwargs.recurrent must be true or false, got 'no'"),
    ({"policy_kwargs": {"mixed_precision": 1}}, "policy_kwargs.mixed_precision must be true or false"),
    ({"policy_kwargs": {"communication": 3}}, r"communication must be one of \(.*\), got 3"),
]


@pytest.mark.parametrize("kwargs, message", WRONG_TYPES)
@pytest.mark.parametrize("algorithm", [SoftHGRN, SACHGRN])
def test_arguments_of_a_wrong_type_raise_naming_the_argument(algorithm, small_env, kwargs, message):
    with pytest.raises((TypeError, ValueError), match=message):
        algorithm("GraphPolicy", small_env, **{"batch_size": 32, **kwargs})


@pytest.mark.parametrize(
    "algorithm, policy_kwargs, message",
    [
        (SoftHGRN, {"average_tau": "0.1"}, "policy_kwargs.average_tau must be a number or None, got '0.1'"),
        (SACHGRN, {"n_critics": 2.0}, "policy_kwargs.n_critics must be an integer, got 2.0"),
        (SACHGRN, {"tempered_actor": "yes"}, "policy_kwargs.tempered_actor must be true or false"),
        (
            SACHGRN,
            {"actor_kwargs": {"hidden_dim": "x"}},
            "policy_kwargs.actor_kwargs.hidden_dim must be an integer, got 'x'",
        ),
        (
            SACHGRN,
            {"critic_kwargs": {"n_critics": 2}},
            "policy_kwargs.critic_kwargs.n_critics is not a network option; the network options: ",
        ),
    ],
)
def test_policy_arguments_of_each_algorithm_are_checked(algorithm, small_env, policy_kwargs, message):
    with pytest.raises(TypeError, match=message):
        algorithm("GraphPolicy", small_env, batch_size=32, policy_kwargs=policy_kwargs)


def test_good_algorithm_arguments_pass(small_env):
    model = SoftHGRN("GraphPolicy", small_env, learning_rate=lambda progress: 1e-3 * progress, gamma=1,
                     buffer_size=160, batch_size=32, train_freq=(1, "episode"))  # fmt: skip
    assert model.replay_buffer.buffer_size == 32


@pytest.mark.parametrize("n_envs", [2.5, "2", 0, True])
def test_make_graph_vec_env_needs_a_positive_integer_n_envs(n_envs):
    with pytest.raises(
        ValueError, match=f"n_envs must be a positive integer \\(env copies\\), got {n_envs!r}"
    ):
        make_graph_vec_env("surviving_v0", n_envs=n_envs)


def test_train_with_train_freq_0_exits_at_once_naming_it(tmp_path):
    """It used to hang: collection never ended (a subprocess, so a hang fails the test)."""
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    command = [sys.executable, "-m", "sb3_hgrn", *train_args(tmp_path), "--param", "train_freq=0"]
    done = subprocess.run(command, capture_output=True, text=True, env=env, timeout=60)
    assert done.returncode == 2 and "train_freq must be an integer >= 1" in done.stderr
    assert not (tmp_path / "surviving_v0").exists()


def test_load_of_the_other_algorithm_says_which_class_to_use(finished_root, small_env, tmp_path):
    soft = run_of(finished_root) / "model.zip"
    sac = tmp_path / "sac.zip"
    SACHGRN("GraphPolicy", small_env, batch_size=4).save(sac)
    with pytest.raises(
        ValueError, match="holds a SACHGRN model, not a SoftHGRN one: load it with SACHGRN.load"
    ):
        SoftHGRN.load(sac)
    with pytest.raises(
        ValueError, match="holds a SoftHGRN model, not a SACHGRN one: load it with SoftHGRN.load"
    ):
        SACHGRN.load(soft)
    assert isinstance(SACHGRN.load(sac), SACHGRN) and isinstance(SoftHGRN.load(soft), SoftHGRN)


BUFFER_ARRAYS = ("observations", "next_observations", "neighbors", "actions", "rewards", "hidden",
                 "episode_starts")  # fmt: skip


def assert_same_rows(buffer, other, rows: int) -> None:
    """The first ``rows`` steps of two replay buffers hold the same transitions."""
    for name in BUFFER_ARRAYS:
        assert (getattr(buffer, name)[:rows] == getattr(other, name)[:rows]).all(), name


def test_replay_buffer_round_trip_across_a_load(small_env, tmp_path):
    model = SoftHGRN("GraphPolicy", small_env, batch_size=4, seed=0)
    model.learn(150)
    model.save(tmp_path / "model.zip")
    model.save_replay_buffer(tmp_path / "buffer.pkl")
    loaded = SoftHGRN.load(tmp_path / "model.zip", env=small_env)
    loaded.load_replay_buffer(tmp_path / "buffer.pkl")
    buffer, original = loaded.replay_buffer, model.replay_buffer
    assert (buffer.pos, buffer.full) == (original.pos, original.full) and buffer.pos > 0
    assert_same_rows(buffer, original, buffer.buffer_size)
    np.random.seed(0)
    first = original.sample(8)
    np.random.seed(0)
    assert all((a == b).all() for a, b in zip(first[:-1], buffer.sample(8)[:-1], strict=True))


def test_a_loaded_replay_buffer_samples_the_loading_models_returns(small_env, tmp_path):
    SoftHGRN("GraphPolicy", small_env, batch_size=4).learn(50).save_replay_buffer(tmp_path / "buffer.pkl")
    model = SoftHGRN("GraphPolicy", small_env, batch_size=4, n_steps=3, gamma=0.5)
    model.load_replay_buffer(tmp_path / "buffer.pkl")
    assert (model.replay_buffer.n_steps, model.replay_buffer.gamma) == (3, 0.5)
    assert set(model.replay_buffer.sample(64).discounts[:, 0].tolist()) <= {0.5, 0.25, 0.125}


def test_load_replay_buffer_of_another_agent_count_says_what_differs(small_env, tmp_path):
    model = SoftHGRN("GraphPolicy", small_env, batch_size=4)
    model.save_replay_buffer(tmp_path / "buffer.pkl")
    other = make_graph_vec_env("surviving_v0", env_kwargs={"n_agents": 6, "map_size": 10})
    with pytest.raises(ValueError, match=r"does not fit this model: slots 5 \(model 6\), agents per copy 5"):
        SoftHGRN("GraphPolicy", other, batch_size=4).load_replay_buffer(tmp_path / "buffer.pkl")
    with pytest.raises(TypeError, match="holds a dict, not a GraphReplayBuffer"):
        save_to_pkl(tmp_path / "dict.pkl", {})
        model.load_replay_buffer(tmp_path / "dict.pkl")


def test_a_run_resumed_with_its_replay_buffer_continues_it(tmp_path):
    """An uninterrupted run's buffer at 100 agent-steps is the start of a run resumed from there."""
    assert main(train_args(tmp_path, 200, "--save-replay-buffer")) == 0
    checkpoints = run_of(tmp_path) / "checkpoints"
    assert sorted(path.name for path in checkpoints.glob("*replay_buffer*")) == [
        "model_replay_buffer_100_steps.pkl", "model_replay_buffer_200_steps.pkl"
    ]  # fmt: skip
    at_100, at_200 = (load_from_pkl(checkpoints / f"model_replay_buffer_{n}_steps.pkl") for n in (100, 200))
    assert (at_100.pos, at_200.pos) == (20, 40)  # every vec-step up to the checkpoint
    assert_same_rows(at_100, at_200, 20)
    as_killed(run_of(tmp_path))
    (checkpoints / "model_200_steps.zip").unlink()
    captured = {}

    def record_buffer(self, *args, **kwargs):
        captured["buffer"] = copy.deepcopy(self.replay_buffer)
        return learn(self, *args, **kwargs)

    learn = GraphOffPolicyAlgorithm.learn
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(GraphOffPolicyAlgorithm, "learn", record_buffer)
        assert main(train_args(tmp_path, 200, "--save-replay-buffer")) == 0
    assert captured["buffer"].pos == 20
    assert_same_rows(captured["buffer"], at_100, captured["buffer"].buffer_size)
    resumed = load_from_pkl(checkpoints / "model_replay_buffer_200_steps.pkl")
    assert resumed.pos == 40
    assert_same_rows(resumed, at_200, resumed.buffer_size)  # with the training state: exactly


BAD_OBSERVATIONS = [
    (float("nan"), r"the non-finite value nan at obs index 0"),
    (float("inf"), r"the non-finite value inf at obs index 0"),
    (1e6, r"the value 1000000.0 at obs index 0, outside the observation space \[-1.0, 1.0\]"),
]


@pytest.mark.parametrize("value, problem", BAD_OBSERVATIONS)
@pytest.mark.parametrize("algorithm", [SoftHGRN, SACHGRN])
def test_a_bad_observation_while_learning_names_the_agent_and_step(algorithm, value, problem):
    env = make_graph_vec_env(lambda: BadValueEnv(value), n_envs=2)
    model = algorithm("GraphPolicy", env, batch_size=4, learning_starts=0)
    with pytest.raises(ValueError, match=f"{problem} for agent 1 of env copy 0 \\(slot 1\\) at step 3 of"):
        model.learn(60)


def test_float_neighbour_indices_are_refused():
    with pytest.raises(
        ValueError, match=r"the neighbour index 0.5, not a whole number for agent 0 .* step 0"
    ):
        make_graph_vec_env(lambda: BadValueEnv(offset=0.5)).reset()
    env = make_graph_vec_env(lambda: BadValueEnv(offset=0.0))  # whole numbers as floats pass
    assert env.reset()["neighbors"].dtype == np.int32


@pytest.fixture(scope="module")
def predicting():
    """A model on 2 copies of :class:`DictOnlyEnv` and a first observation of its env."""
    env = make_graph_vec_env(DictOnlyEnv, n_envs=2)
    return SoftHGRN("GraphPolicy", env, batch_size=4, policy_kwargs={"hidden_dim": 16}), env.reset()


@pytest.mark.parametrize("value, problem", BAD_OBSERVATIONS)
@pytest.mark.parametrize("deterministic", [False, True])
def test_a_bad_observation_in_predict_names_the_agent(predicting, value, problem, deterministic):
    model, observation = predicting
    observation = {key: array.copy() for key, array in observation.items()}
    observation["obs"][4, 0] = value
    with pytest.raises(
        ValueError, match=f"predict\\(\\) got {problem} for agent 1 of env copy 1 \\(slot 4\\)"
    ):
        model.predict(observation, deterministic=deterministic)


def test_float_neighbour_indices_in_predict_are_refused(predicting):
    model, observation = predicting
    neighbors = observation["neighbors"] + 0.5
    with pytest.raises(
        ValueError, match="the neighbour index 0.5, not a whole number for agent 0 of env copy 0"
    ):
        model.predict({**observation, "neighbors": neighbors})
    with pytest.raises(ValueError, match=r"the neighbour index 3, not one of the agent indices in \[-1, 2\]"):
        model.predict({**observation, "neighbors": observation["neighbors"] + 1})


def test_evaluate_on_nan_rewards_raises_naming_the_agent_and_step():
    env = make_graph_vec_env(lambda: DictOnlyEnv(reward=float("nan")))
    with pytest.raises(
        ValueError, match=r"non-finite rewards: nan for agent 0 of env copy 0 \(slot 0\) at step 1 "
    ):
        evaluate_graph_policy(RandomGraphPolicy(env, seed=0), env, n_eval_episodes=1)


@pytest.mark.parametrize("reward", [3e38, -2e12])
@pytest.mark.parametrize("algorithm", [SoftHGRN, SACHGRN])
def test_an_extreme_reward_while_learning_names_the_agent_and_the_bound(algorithm, reward):
    env = make_graph_vec_env(lambda: DictOnlyEnv(reward=reward / 2), n_envs=1)
    model = algorithm("GraphPolicy", env, batch_size=4, learning_starts=0, seed=0)
    with pytest.raises(ValueError, match=r"rewards beyond the bound \|reward\| <= 1e\+12: .* for agent \d"):
        model.learn(60)


def test_evaluate_refuses_an_extreme_reward():
    env = make_graph_vec_env(lambda: DictOnlyEnv(reward=1e13))
    with pytest.raises(ValueError, match=r"rewards beyond the bound .* at step 1 of the evaluation"):
        evaluate_graph_policy(RandomGraphPolicy(env, seed=0), env, n_eval_episodes=1)


def test_rewards_at_the_bound_train_to_finite_parameters():
    """Actions 0..2 earn 0, 5e11 or 1e12 (the largest reward allowed) per agent-step."""
    env = make_graph_vec_env(lambda: DictOnlyEnv(reward=MAX_ABS_REWARD / 2), n_envs=2)
    model = SoftHGRN("GraphPolicy", env, batch_size=4, learning_starts=12, train_freq=1, seed=0)
    model.learn(300)
    assert model._n_updates > 40
    assert all(th.isfinite(parameter).all() for parameter in model.policy.parameters())


@pytest.mark.parametrize(
    "policy, error, message",
    [
        (
            None,
            TypeError,
            "policy must be one of the names 'GraphPolicy' or a subclass of SoftHGRNPolicy, got None",
        ),
        (3, TypeError, "policy must be one of the names 'GraphPolicy' .* got 3"),
        (dict, TypeError, "got <class 'dict'>"),
        (SACHGRNPolicy, TypeError, "a subclass of SoftHGRNPolicy"),
        (
            "MlpPolicy",
            ValueError,
            "Unknown policy 'MlpPolicy': policy must be one of the names 'GraphPolicy'",
        ),
    ],
)
def test_a_value_that_is_no_policy_names_the_accepted_ones(small_env, policy, error, message):
    with pytest.raises(error, match=message):
        SoftHGRN(policy, small_env, batch_size=4)


def test_predict_states_the_expected_shapes_of_state_and_episode_start(predicting):
    model, observation = predicting
    _, state = model.predict(observation)
    assert state[0].shape == (1, 6, 16)
    with pytest.raises(
        ValueError, match=r"state must be the tuple \(hidden,\) .* got an array of shape \(1, 6, 16\)"
    ):
        model.predict(observation, state=state[0])
    with pytest.raises(ValueError, match=r"state\[0\] has shape \(1, 3, 16\), expected \(1, 6, 16\)"):
        model.predict(observation, state=(state[0][:, :3],))
    with pytest.raises(
        ValueError, match=r"episode_start has shape \(4,\), expected \(6,\): one flag per slot"
    ):
        model.predict(observation, state=state, episode_start=np.ones(4, dtype=bool))
    actions, _ = model.predict(observation, state=state, episode_start=np.zeros(6, dtype=bool))
    assert actions.shape == (6,)


NOT_A_GRAPH_BATCH = [
    (lambda obs: "hello", TypeError, r"observation must be a dict .*'obs' and 'neighbors'.*, got a str"),
    (lambda obs: obs["obs"], TypeError, r"observation must be a dict .*, got an array of shape \(6, 2\)"),
    (lambda obs: {"obs": obs["obs"]}, ValueError, "observation lacks the key 'neighbors'"),
    (
        lambda obs: {**obs, "obs": obs["obs"].astype(str)},
        TypeError,
        r"observation\['obs'\] must hold numbers, got dtype <U",
    ),
    (
        lambda obs: {**obs, "neighbors": obs["neighbors"].astype(str)},
        TypeError,
        r"observation\['neighbors'\] must hold numbers, got dtype <U",
    ),
    (
        lambda obs: {**obs, "obs": obs["obs"][:, :1]},
        ValueError,
        r"observation\['obs'\] has shape \(6, 1\), expected \(n_slots, 2\)",
    ),
    (
        lambda obs: {**obs, "neighbors": obs["neighbors"][:, 0]},
        ValueError,
        r"observation\['neighbors'\] has shape \(6,\), expected \(6, 3\)",
    ),
]


@pytest.mark.parametrize("make, error, message", NOT_A_GRAPH_BATCH)
def test_predict_refuses_what_is_no_graph_batch_saying_what_it_expects(predicting, make, error, message):
    model, observation = predicting
    with pytest.raises(error, match=message):
        model.predict(make(observation))


def test_predict_refuses_a_state_that_is_not_finite_numbers(predicting):
    model, observation = predicting
    _, (hidden,) = model.predict(observation)
    bad = hidden.copy()
    bad[0, 4, 3] = np.nan
    with pytest.raises(
        ValueError, match=r"state\[0\] holds the non-finite value nan for agent 1 of env copy 1 \(slot 4\)"
    ):
        model.predict(observation, state=(bad,))
    with pytest.raises(TypeError, match=r"state\[0\] must hold numbers, got dtype <U"):
        model.predict(observation, state=(hidden.astype(str),))
    with pytest.raises(TypeError, match=r"episode_start must hold booleans \(or 0 and 1\), got dtype <U"):
        model.predict(observation, state=(hidden,), episode_start=np.array(["a"] * 6))


def test_infinite_observations_are_refused_in_an_unbounded_space():
    space = gymnasium.spaces.Box(-np.inf, np.inf, shape=(2,), dtype=np.float32)
    observations = {"obs": np.array([[0.0, 1.0], [0.0, -np.inf]]), "neighbors": np.array([[0], [1]])}
    assert observation_problem(observations, space, 2) == (1, "the non-finite value -inf at obs index 1")
    assert observation_problem({**observations, "obs": np.zeros((2, 2))}, space, 2) is None


def point_at_controller(folder: Path, controller: str) -> None:
    """Make the run in ``folder`` a Pursuit run whose ``config.yml`` sets ``prey_controller``."""
    data = yaml.safe_load((folder / "config.yml").read_text())
    data.update(env="pursuit_v0", env_kwargs={"learners": "predator", "prey_controller": controller})
    (folder / "config.yml").write_text(yaml.safe_dump(data))


def test_evaluate_refuses_a_controller_a_config_points_outside_the_run(root, tmp_path, monkeypatch, capsys):
    folder = run_of(root)
    outside = tmp_path / "elsewhere" / "prey.zip"
    point_at_controller(folder, str(outside))
    loads = []
    monkeypatch.setattr(saved_controllers, "load_controller", lambda *args: loads.append(args))
    error = fails_with(["evaluate", str(folder), "--episodes", "1"], capsys)
    assert f"sets prey_controller='{outside}', a model outside the run folder" in error
    assert (
        "can run code" in error and "--trust-config" in error and "--env-param prey_controller=PATH" in error
    )
    assert loads == []


@pytest.mark.parametrize(
    "controller, given, trusted",
    [("evader", (), False), ("INSIDE", (), False), ("OUTSIDE", ("prey_controller",), False),
     ("OUTSIDE", (), True)],
)  # fmt: skip
def test_controllers_inside_the_run_given_or_trusted_pass(root, tmp_path, controller, given, trusted):
    folder = run_of(root)
    path = {"INSIDE": str(folder / "checkpoints" / "model_100_steps"), "OUTSIDE": str(tmp_path / "x.zip")}
    point_at_controller(folder, path.get(controller, controller))
    config = RunConfig.from_dict(yaml.safe_load((folder / "config.yml").read_text()))
    check_stored_model_paths(config, folder, given, trusted)


def test_resume_skips_a_damaged_replay_buffer(tmp_path):
    assert main(train_args(tmp_path, 200, "--save-replay-buffer")) == 0
    folder = run_of(tmp_path)
    as_killed(folder)
    cut_short(folder / "checkpoints" / "model_replay_buffer_200_steps.pkl")
    with pytest.warns(UserWarning, match="Skipping the replay buffer .*model_replay_buffer_200_steps.pkl"):
        assert main(train_args(tmp_path, 200, "--save-replay-buffer")) == 0
    assert json.loads((folder / "eval.json").read_text())["resumed_from"] == "model_200_steps.zip"


@pytest.mark.parametrize("algorithm", [SoftHGRN, SACHGRN])
def test_a_compiled_model_trains_saves_and_loads_compiled(algorithm, small_env, tmp_path):
    """``policy_kwargs=dict(compile_network=...)`` trains, is saved with the option, loads compiled,
    and acts as the same model with its networks eager."""
    model = algorithm(
        "GraphPolicy", small_env, learning_starts=10, batch_size=4, train_freq=2, seed=0,
        policy_kwargs={"hidden_dim": 8, "n_heads": 2, "compile_network": {"backend": "aot_eager"}},
    )  # fmt: skip
    model.learn(60)
    model.save(tmp_path / "model.zip")
    loaded = algorithm.load(tmp_path / "model.zip", env=small_env)
    networks = [module for module in loaded.policy.modules() if isinstance(module, HGRN)]
    assert networks and all(network.compile_options == {"backend": "aot_eager"} for network in networks)
    obs = small_env.reset()
    compiled_actions, compiled_state = loaded.predict(obs, deterministic=True)
    for network in networks:
        network.compile_options = None
    eager_actions, eager_state = loaded.predict(obs, deterministic=True)
    np.testing.assert_array_equal(compiled_actions, eager_actions)
    np.testing.assert_allclose(compiled_state, eager_state, atol=1e-5)
