"""Backends of the sweeps (local processes, Ray tasks) and the ``sb3-hgrn sweep`` grid."""

import _thread
import csv
import json
import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path

import pytest

from sb3_hgrn.cli import main
from sb3_hgrn.experiments import backends
from sb3_hgrn.experiments.backends import LocalBackend
from sb3_hgrn.experiments.cells import format_number
from sb3_hgrn.experiments.config import ConfigError
from sb3_hgrn.experiments.jobs import Job, run_jobs
from sb3_hgrn.experiments.lock import lock_holder
from sb3_hgrn.experiments.run_folder import read_eval
from sb3_hgrn.experiments.sweep import (
    Point,
    SweepSettings,
    check_settings,
    grid_points,
    parse_grid,
    read_grid_file,
    run_grid,
    split_values,
)
from sb3_hgrn.experiments.table1 import run_sweep

REPO = Path(__file__).resolve().parents[1]
CHILD_ENV = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
TABLE = {"budget": "ci", "n_seeds": 1, "presets": ["dqn", "soft_hgrn"], "envs": ["uav_mbs_v0"], "jobs": 2}
GONE_WITHIN_S = 30
"""Seconds within which a stopped run's processes must be gone, with both cores busy."""
START_WITHIN_S = 300
"""Seconds a run may take to start (and lock its folder) on a loaded machine."""


def test_grid_values_split_and_parse(tmp_path):
    assert split_values("1e-3, 3e-4") == ["1e-3", "3e-4"]
    assert split_values("[1,2],{a: 1, b: 2},x") == ["[1,2]", "{a: 1, b: 2}", "x"]
    assert parse_grid(["learning_rate=1e-3,3e-4", "policy_kwargs.hidden_dim=16"]) == {
        "learning_rate": [0.001, 0.0003],
        "policy_kwargs.hidden_dim": [16],
    }
    for bad in ["learning_rate", "learning_rate=", "learning_rate=1e-3,", "=1,2"]:
        with pytest.raises(ConfigError, match="Malformed --grid"):
            parse_grid([bad])

    path = tmp_path / "sweep.yml"
    path.write_text("presets: dqn\nseeds: 2\ngrid: {learning_rate: [1e-3, 0.5]}\nenv_grid: {n_agents: [4]}\n")
    spec = read_grid_file(path)
    assert spec["grid"] == {"learning_rate": [0.001, 0.5]}  # YAML leaves 1e-3 a string; read as a number
    assert spec["presets"] == ["dqn"] and spec["seeds"] == 2 and spec["env_grid"] == {"n_agents": [4]}
    for text, message in [
        ("grids: {}", "unknown key"),
        ("grid: {learning_rate: 0.1}", "non-empty list"),
        ("seeds: two", "positive number of seeds"),
        ("grid: [1]", "must be a mapping"),
    ]:
        path.write_text(text)
        with pytest.raises(ConfigError, match=message):
            read_grid_file(path)


def test_grid_points_name_their_folders():
    points = grid_points(
        {"learning_rate": [0.001, 1e-05], "policy_kwargs.hidden_dim": [8]}, {"n_agents": [4]}
    )
    assert [point.name() for point in points] == [
        "learning_rate=0.001,policy_kwargs.hidden_dim=8,env.n_agents=4",
        "learning_rate=1e-05,policy_kwargs.hidden_dim=8,env.n_agents=4",
    ]
    assert points[0].train_args() == [
        "--param",
        "learning_rate=0.001",
        "policy_kwargs.hidden_dim=8",
        "--env-param",
        "n_agents=4",
    ]
    assert grid_points({}, {}) == [Point()] and Point().name() == "default" and Point().train_args() == []
    with pytest.raises(ConfigError, match="twice"):
        grid_points({"learning_rate": [0.001, 1e-3]}, {})


def test_sweep_refuses_bad_input_before_training(tmp_path):
    settings = SweepSettings("uav_mbs_v0", "ci")
    with pytest.raises(ConfigError, match="takes no argument 'learning_rat'"):
        run_grid(settings, ["soft_hgrn"], 1, {"learning_rat": [0.1]}, folder=tmp_path)
    with pytest.raises(ConfigError, match="no values"):
        run_grid(settings, ["soft_hgrn"], 1, {"learning_rate": []}, folder=tmp_path)
    assert not list(tmp_path.iterdir())


def test_a_folder_keeps_the_shared_settings_of_its_sweep(tmp_path):
    settings = SweepSettings("uav_mbs_v0", "ci", 600, {"policy_kwargs": {"hidden_dim": 8}}, {"n_users": 20})
    check_settings(tmp_path, settings)
    check_settings(tmp_path, settings)  # the same settings: accepted
    recorded = (tmp_path / "sweep.yml").read_text()
    for other in (
        replace(settings, timesteps=900),
        replace(settings, env_params={}),
        replace(settings, budget="cpu"),
    ):
        with pytest.raises(ConfigError, match="other shared settings"):
            check_settings(tmp_path, other)
    assert (tmp_path / "sweep.yml").read_text() == recorded


def test_sweep_trains_the_grid_with_local_processes_and_no_ray(tmp_path):
    args = ["sweep", "--env", "uav_mbs_v0", "--budget", "ci", "--presets", "soft_hgrn", "--seeds", "1"]
    args += ["--timesteps", "360", "--grid", "batch_size=4,8", "--env-param", "n_users=20"]
    args += ["--folder", str(tmp_path), "--jobs", "2"]
    script = f"import sys; from sb3_hgrn.cli import main; s = main({args!r}); "
    script += "assert 'ray' not in sys.modules, 'ray imported'; sys.exit(s)"
    done = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, env=CHILD_ENV, timeout=300
    )
    assert done.returncode == 0, done.stdout + done.stderr
    assert "2 runs, 0 already done, 2 to run, 2 at a time (local backend)" in done.stdout

    runs = {
        point: tmp_path / point / "uav_mbs_v0" / "soft_hgrn" / "seed_0"
        for point in ("batch_size=4", "batch_size=8")
    }
    for point, folder in runs.items():
        done_eval = json.loads((folder / "eval.json").read_text())
        assert done_eval["completed"] and done_eval["agent_steps"] == 360 and done_eval["n_agents"] == 6
        config = (folder / "config.yml").read_text()
        assert f"batch_size: {point[-1]}" in config and "n_users: 20" in config
    rows = list(csv.DictReader((tmp_path / "sweep.csv").open()))
    assert [(row["point"], row["preset"], row["batch_size"]) for row in rows] == [
        ("batch_size=4", "soft_hgrn", "4"),
        ("batch_size=8", "soft_hgrn", "8"),
    ]
    for row, folder in zip(rows, runs.values(), strict=True):
        score = json.loads((folder / "eval.json").read_text())["mean"]
        assert float(row["mean"]) == pytest.approx(score, abs=1e-4) and row["std"] == ""
        assert row["iqm"] == row["iqm_low"] == row["iqm_high"] == row["mean"]  # one seed: no spread
        assert row["seeds_done"] == row["seeds"] == "1" and row["agent_steps"] == "360"
    table = (tmp_path / "sweep.md").read_text()
    assert "# Sweep on `uav_mbs_v0`, budget `ci`" in table and "`n_users=20`" in table
    assert f"| `batch_size=4` | soft_hgrn | {format_number(float(rows[0]['mean']))} [" in table

    kept = (runs["batch_size=4"] / "eval.json").stat().st_mtime_ns
    assert main(args) == 0  # everything is done: nothing runs again
    assert (runs["batch_size=4"] / "eval.json").stat().st_mtime_ns == kept


def test_backend_options_give_clear_errors(tmp_path, monkeypatch, capsys):
    table = ["reproduce", "table1", "--budget", "ci", "--folder", str(tmp_path)]
    with pytest.raises(SystemExit):
        main([*table, "--cpus-per-run", "2"])
    assert "apply to --backend ray only" in capsys.readouterr().err
    sweep = ["sweep", "--env", "uav_mbs_v0", "--budget", "ci", "--folder", str(tmp_path / "sweep")]
    grid_file = tmp_path / "grid.yml"
    grid_file.write_text("grid: {learning_rat: [1e-3]}\n")
    for extra, message in [
        (["--grid", "batch_size"], "Malformed --grid 'batch_size'"),
        (["--env-grid", "n_users=,"], "Malformed --env-grid"),
        (["--grid-file", str(tmp_path / "none.yml")], "Cannot read the grid file"),
        (["--presets", "nope"], "Unknown preset 'nope'"),
        (["--grid-file", str(grid_file)], "takes no argument 'learning_rat'"),
    ]:
        with pytest.raises(SystemExit):
            main([*sweep, *extra])
        assert message in capsys.readouterr().err
    assert not (tmp_path / "sweep").exists()
    monkeypatch.setitem(sys.modules, "ray", None)  # as if ray were not installed
    with pytest.raises(SystemExit):
        main([*table, "--backend", "ray"])
    assert "pip install 'sb3_hgrn[ray]'" in capsys.readouterr().err


@pytest.fixture(scope="module")
def local_ray():
    ray = pytest.importorskip("ray")
    ray.init(num_cpus=2, include_dashboard=False)
    yield ray
    ray.shutdown()


def _layout(root: Path) -> set[str]:
    """Relative paths under ``root``, with the TensorBoard event files (named by time and host) as one."""
    return {
        str(path.relative_to(root)) if "tfevents" not in path.name else str(path.parent.relative_to(root))
        for path in root.rglob("*")
    }


def _rows(root: Path) -> list[dict[str, str]]:
    rows = list(csv.DictReader((root / "table1.csv").open()))
    for row in rows:
        del row["wall_time_s"]
    return rows


def test_ray_backend_reproduces_the_local_table(local_ray, tmp_path):
    from sb3_hgrn.experiments.backends import RayBackend

    messages = []
    assert run_sweep(**TABLE, folder=tmp_path / "local", threads=1, backend=LocalBackend()) == []
    assert run_sweep(**TABLE, folder=tmp_path / "ray", backend=RayBackend(), log=messages.append) == []
    assert any("2 to run, 2 at a time (ray backend)" in message for message in messages)
    assert _layout(tmp_path / "local") == _layout(tmp_path / "ray")
    assert len([path for path in _layout(tmp_path / "ray") if path.endswith("eval.json")]) == 3
    assert _rows(tmp_path / "local") == _rows(tmp_path / "ray")
    table = (tmp_path / "ray" / "table1.md").read_text().split("Summed wall time")[0]
    assert table == (tmp_path / "local" / "table1.md").read_text().split("Summed wall time")[0]


@pytest.mark.skipif(
    not os.environ.get("SB3_HGRN_FULL_TABLE"),
    reason="the whole ci Table 1 twice takes minutes; set SB3_HGRN_FULL_TABLE=1 to run it",
)
def test_ray_backend_reproduces_the_whole_ci_table(local_ray, tmp_path):
    """Every preset on every env, 3 seeds, at budget ci: the same folders and table on both backends."""
    from sb3_hgrn.experiments.backends import RayBackend

    table = {"budget": "ci", "n_seeds": 3, "jobs": 2}
    assert run_sweep(**table, folder=tmp_path / "local", threads=1, backend=LocalBackend()) == []
    assert run_sweep(**table, folder=tmp_path / "ray", backend=RayBackend()) == []
    assert _layout(tmp_path / "local") == _layout(tmp_path / "ray")
    evaluations = [path for path in _layout(tmp_path / "ray") if path.endswith("eval.json")]
    assert len(evaluations) == 12 * 3 * 3 + 3 * 3  # every run, and the random anchor of each env and seed
    assert _rows(tmp_path / "local") == _rows(tmp_path / "ray")
    markdown = [
        (tmp_path / side / "table1.md").read_text().split("Summed wall time")[0] for side in ("local", "ray")
    ]
    assert markdown[0] == markdown[1]


# --- stopping runs: bounded, with both cores busy ----------------------------------------------------


@pytest.fixture
def busy_cores():
    """Two busy-loop processes for the length of a test, as other work on a shared 2-core machine."""
    hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(2)]
    yield
    for hog in hogs:
        hog.kill()
        hog.wait()


def processes_naming(marker: str) -> list[int]:
    """Pids of the living processes whose command line contains ``marker`` (read from /proc)."""
    pids = []
    for entry in Path("/proc").iterdir():
        try:
            command = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:  # not a process, or gone meanwhile
            continue
        if entry.name.isdigit() and marker in command and int(entry.name) != os.getpid():
            pids.append(int(entry.name))
    return pids


def assert_gone(marker: str, since: float) -> None:
    """Fail unless every process naming ``marker`` is gone within ``GONE_WITHIN_S`` s of ``since``
    (those left are killed first, so that a failing test leaves none behind)."""
    while left := processes_naming(marker):
        if time.time() - since > GONE_WITHIN_S:
            for pid in left:
                os.kill(pid, signal.SIGKILL)
            pytest.fail(f"still running {GONE_WITHIN_S} s after the stop: processes {left}")
        time.sleep(0.5)


def call_bounded(function, seconds: float = GONE_WITHIN_S) -> None:
    """Call ``function()`` in a thread; fail (not hang) when it has not returned after ``seconds``."""
    thread = threading.Thread(target=function, daemon=True)
    thread.start()
    thread.join(seconds)
    assert not thread.is_alive(), f"{function} did not return within {seconds} s"


def train_args_into(folder: Path, seed: int = 0) -> list[str]:
    """``train`` arguments of a long run (hours) into the run folders under ``folder``."""
    args = ["train", "--env", "uav_mbs_v0", "--preset", "soft_hgrn", "--budget", "ci", "--seed", str(seed)]
    return [*args, "--timesteps", "100000000", "--threads", "1", "--folder", str(folder)]


def wait_until_started(folders: list[Path], log: Path) -> None:
    """Wait until every run folder is locked: its run has started training."""
    started = time.time()
    while any(lock_holder(folder) is None for folder in folders):
        assert time.time() - started < START_WITHIN_S, log.read_text() if log.exists() else "no log"
        time.sleep(0.5)


STUBBORN = """
import signal, subprocess, sys, time
signal.signal(signal.SIGTERM, signal.SIG_IGN)
if "grandchild" not in sys.argv:
    subprocess.Popen([sys.executable, __file__, "grandchild"])
time.sleep(3600)
"""
"""A run's script that ignores SIGTERM and starts a grandchild that ignores it too."""


def test_a_stopped_local_run_ends_its_whole_process_group(busy_cores, tmp_path, monkeypatch):
    """A run whose processes ignore SIGTERM, one of them a grandchild: stop() kills them all."""
    script = tmp_path / "stubborn.py"
    script.write_text(STUBBORN)
    monkeypatch.setattr(backends, "python_command", lambda args: [sys.executable, str(script), *args])
    marker = str(script)
    run = LocalBackend().start([], tmp_path / "log.txt", threads=1)
    started = time.time()
    while len(processes_naming(marker)) < 2:  # the child and its grandchild
        assert time.time() - started < START_WITHIN_S and run.poll() is None, (
            tmp_path / "log.txt"
        ).read_text()
        time.sleep(0.2)
    started = time.time()
    try:
        call_bounded(run.stop)
    finally:
        assert_gone(marker, started)


def test_a_run_dies_with_the_process_that_started_it(busy_cores, tmp_path):
    """A sweep killed outright (no Ctrl-C to catch) takes its runs with it."""
    folder = tmp_path / "uav_mbs_v0" / "soft_hgrn" / "seed_0"
    script = (
        "import sys, time; from pathlib import Path; from sb3_hgrn.experiments.backends import LocalBackend; "
        f"LocalBackend().start({train_args_into(tmp_path)!r}, Path({str(tmp_path / 'train.log')!r}), 1); "
        "time.sleep(3600)"
    )
    sweep = subprocess.Popen([sys.executable, "-c", script], env=CHILD_ENV)
    try:
        wait_until_started([folder], tmp_path / "train.log")
    finally:
        sweep.kill()
        sweep.wait()
    assert_gone(str(tmp_path), time.time())
    assert read_eval(folder) is None


class LosingRay:
    """Ray as the sweep sees it, but every cancel without ``force`` lost on its way."""

    def __init__(self, ray):
        self.ray = ray

    def __getattr__(self, name):
        return getattr(self.ray, name)

    def cancel(self, ref, force=False):
        if force:
            self.ray.cancel(ref, force=True)


@pytest.mark.parametrize("lost", [False, True], ids=["interrupted", "interrupt-lost"])
def test_a_stopped_ray_task_stops_its_run(local_ray, busy_cores, tmp_path, lost):
    from sb3_hgrn.experiments.backends import RayBackend

    folder = tmp_path / "uav_mbs_v0" / "soft_hgrn" / "seed_0"
    backend = RayBackend()
    if lost:
        backend.ray = LosingRay(local_ray)
    run = backend.start(train_args_into(tmp_path), tmp_path / "train.log", threads=1)
    wait_until_started([folder], tmp_path / "train.log")
    assert run.poll() is None
    started = time.time()
    try:
        call_bounded(run.stop)
    finally:
        assert_gone(str(tmp_path), started)
    assert lock_holder(folder) is None and read_eval(folder) is None


@pytest.mark.parametrize("backend_name", ["local", "ray"])
def test_a_sweep_stopped_with_ctrl_c_leaves_no_run_behind(tmp_path, request, backend_name):
    """Ctrl-C (KeyboardInterrupt in the sweep's main thread) while two runs train: both are gone.
    The local runs start beside two busy cores; the Ray runs without them, because Ray's own
    processes on two loaded cores take minutes to start two runs."""
    request.getfixturevalue("local_ray" if backend_name == "ray" else "busy_cores")
    folders = [tmp_path / "uav_mbs_v0" / "soft_hgrn" / f"seed_{seed}" for seed in (0, 1)]
    jobs = [Job("uav_mbs_v0", "soft_hgrn", seed, folder) for seed, folder in enumerate(folders)]
    pressed, not_started = [], []

    def press_ctrl_c() -> None:
        """Press Ctrl-C once both runs train, or at the latest when waiting for them fails (the
        sweep would otherwise train on for hours instead of the test failing)."""
        try:
            wait_until_started(folders, folders[1] / "train.log")
        except AssertionError as error:
            not_started.append(str(error))
        finally:
            pressed.append(time.time())
            _thread.interrupt_main()

    threading.Thread(target=press_ctrl_c, daemon=True).start()
    with pytest.raises(KeyboardInterrupt):
        run_jobs(
            jobs,
            lambda job: train_args_into(tmp_path, job.seed),
            jobs=2,
            threads=1,
            log=lambda message: None,
            backend=backends.make_backend(backend_name),
        )
    assert_gone(str(tmp_path), pressed[0])
    assert not not_started, f"the runs did not both start within {START_WITHIN_S} s: {not_started[0]}"
    assert all(lock_holder(folder) is None and read_eval(folder) is None for folder in folders)


class RecordingTask:
    """A Ray remote function as the backend uses it, recording the options of each submission."""

    def __init__(self):
        self.submitted: list[dict] = []
        self._options: dict = {}

    def options(self, **options):
        self._options = options
        return self

    def remote(self, *args):
        self.submitted.append(self._options)
        self._options = {}
        return "ref"


def test_a_ray_task_reserves_the_memory_of_its_replay_buffer(tmp_path):
    pytest.importorskip("ray")
    from types import SimpleNamespace

    from sb3_hgrn.cli import train_config
    from sb3_hgrn.experiments.backends import RayBackend
    from sb3_hgrn.experiments.runs import make_env, new_model

    backend = RayBackend()
    backend.ray = SimpleNamespace(is_initialized=lambda: True)  # no Ray instance needed to submit
    backend._task = RecordingTask()
    args = [
        "train",
        "--env",
        "uav_mbs_v0",
        "--preset",
        "soft_hgrn",
        "--budget",
        "ci",
        "--folder",
        str(tmp_path),
    ]
    for buffer_size in (6000, 12000):
        backend.start([*args, "--param", f"buffer_size={buffer_size}"], tmp_path / "train.log", threads=1)
    config = train_config([*args, "--param", "buffer_size=6000"])
    env = make_env(config, config.n_envs, config.seed)
    full = new_model(config, env, verbose=0, tensorboard_log=None, device="cpu").replay_buffer.nbytes
    env.close()
    assert [options["memory"] for options in backend._task.submitted] == [full, 2 * full]
