"""Run folders never lose work: validation before any change, refused resumes, moved-aside runs."""

import shutil
from pathlib import Path

import pytest

from sb3_hgrn.cli import main
from sb3_hgrn.common.off_policy import GraphOffPolicyAlgorithm
from sb3_hgrn.experiments.callbacks import rewind_team_returns

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


def test_overwrite_moves_the_old_run_aside_until_the_new_one_finishes(root, monkeypatch):
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
    assert sorted(path.name for path in folder.parent.iterdir()) == ["seed_0", aside.name]  # the first stays
    assert (aside / "eval.json").read_bytes() == old_eval


def test_rewind_team_returns_drops_rows_after_the_checkpoint(tmp_path):
    path = tmp_path / "team_returns.csv"
    header = '#{"t_start": 0, "env_id": "x", "n_agents": 5, "n_copies": 1}\nr,l,t\n'
    path.write_text(header + "1.0,20,0.1\n2.0,20,0.2\n3.0,20,0.3\n4.0,2")  # the last row cut short
    assert rewind_team_returns(path, 200) == 2
    assert path.read_text() == header + "1.0,20,0.1\n2.0,20,0.2\n"
    assert rewind_team_returns(path, 1000) == 0 and rewind_team_returns(tmp_path / "missing.csv", 0) == 0
