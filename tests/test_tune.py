"""``sb3-hgrn tune`` (Optuna search of one preset on one env) and ``train --config``."""

import csv
from pathlib import Path

import pytest
import yaml

from sb3_hgrn.cli import main
from sb3_hgrn.experiments.config import ConfigError, load_config_file, resolve_config

TOY = ["--env", "surviving_v0", "--preset", "soft_hgrn", "--budget", "ci", "--threads", "1"]
SPACE = """
soft_hgrn:
  learning_rate: {type: loguniform, low: 1.0e-4, high: 3.0e-3}
  batch_size: {type: categorical, choices: [4, 8]}
  gamma: {type: uniform, low: 0.9, high: 0.99}
  policy_kwargs.hidden_dim: {type: categorical, choices: [16, 24]}
"""


@pytest.fixture
def optuna():
    return pytest.importorskip("optuna")


def write(path: Path, text: str) -> Path:
    path.write_text(text, encoding="utf-8")
    return path


# --- train --config -------------------------------------------------------------------------------


def test_config_file_is_merged_over_the_packaged_one(tmp_path):
    path = write(
        tmp_path / "mine.yml",
        "env_kwargs: {n_agents: 5}\n"
        "soft_hgrn: {batch_size: 16, policy_kwargs: {hidden_dim: 24}}\n"
        "budgets:\n  ci: {eval_episodes: 3, env_kwargs: {max_cycles: 10}}\n",
    )
    packaged = resolve_config("surviving_v0", "soft_hgrn", "ci")
    config = resolve_config("surviving_v0", "soft_hgrn", "ci", config_file=path)
    assert packaged.hyperparams["batch_size"] == 8  # the packaged budget's default ...
    assert config.hyperparams["batch_size"] == 16  # ... gives way to the file's top-level preset section
    assert config.hyperparams["policy_kwargs"] == {"hidden_dim": 24}
    assert config.hyperparams["learning_starts"] == packaged.hyperparams["learning_starts"]
    assert config.env_kwargs == {**packaged.env_kwargs, "n_agents": 5, "max_cycles": 10}
    assert config.eval_episodes == 3 and packaged.eval_episodes == 2
    assert config.total_timesteps == packaged.total_timesteps
    other = resolve_config("surviving_v0", "sac_hgrn", "ci", config_file=path)
    assert other.hyperparams == resolve_config("surviving_v0", "sac_hgrn", "ci").hyperparams
    overridden = resolve_config(
        "surviving_v0",
        "soft_hgrn",
        "ci",
        params={"batch_size": 4},
        env_params={"n_agents": 7},
        config_file=path,
    )
    assert overridden.hyperparams["batch_size"] == 4 and overridden.env_kwargs["n_agents"] == 7


@pytest.mark.parametrize(
    "text, message",
    [
        ("soft_hgrn: [1, 2]\n", "section 'soft_hgrn' must be a mapping"),
        ("sof_hgrn: {batch_size: 4}\n", "unknown key 'sof_hgrn'"),
        ("budgets: {huge: {}}\n", "Unknown budget 'huge'"),
        ("budgets: {ci: {n_envs: 0}}\n", "n_envs must be a positive integer"),
        ("budgets: [ci]\n", "budgets must be a mapping"),
        ("soft_hgrn: {batch_size: 4\n", "not valid YAML"),
        ("- 1\n", "must be a mapping"),
    ],
)
def test_bad_config_files_are_refused(tmp_path, text, message):
    with pytest.raises(ConfigError, match=message):
        load_config_file(write(tmp_path / "bad.yml", text))


def test_train_refuses_a_missing_config_file(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["train", *TOY, "--config", str(tmp_path / "none.yml"), "--folder", str(tmp_path)])
    assert exit_info.value.code == 2
    assert "Cannot read the config file" in capsys.readouterr().err
    assert not (tmp_path / "surviving_v0").exists()


# --- search spaces --------------------------------------------------------------------------------


def test_packaged_search_spaces_load(optuna):
    from sb3_hgrn.experiments.tune import load_search_space

    for preset in ("soft_hgrn", "sac_hgrn"):
        space = load_search_space(preset)
        assert {"learning_rate", "batch_size", "gamma", "tau", "target_entropy_ratio"} <= set(space)
        assert space["learning_rate"].log
    assert "policy_kwargs.n_critics" in load_search_space("sac_hgrn")


@pytest.mark.parametrize(
    "entry, message",
    [
        ("learning_rat: {type: uniform, low: 0.1, high: 0.2}", "takes no argument 'learning_rat'"),
        ("seed: {type: int, low: 0, high: 3}", "'seed' is set by the runner"),
        ("policy_kwargs.hiden_dim: {type: int, low: 8, high: 32}", "takes no argument 'hiden_dim'"),
        ("gamma: {type: normal, low: 0.9, high: 0.99}", "unknown distribution type 'normal'"),
        ("gamma: 0.9", "gamma must be a mapping with a type"),
        (
            "gamma: {type: uniform, low: 0.9}",
            r"gamma \(uniform\) takes high, low and optionally step; got low\.",
        ),
        ("gamma: {type: uniform, low: 0.9, high: 0.99, log: true}", "optionally step; got high, log, low"),
        ("gamma: {type: uniform, low: 0.99, high: 0.9}", "bad distribution for gamma"),
        ("gamma: {type: uniform, low: a, high: 0.9}", "must be numbers"),
        ("learning_rate: {type: loguniform, low: 0.0, high: 0.1}", "bad distribution for learning_rate"),
        ("batch_size: {type: int, low: 4.5, high: 8}", "must be integers"),
        ("batch_size: {type: int, low: 4, high: 64, log: yes please}", "log must be true or false"),
        ("batch_size: {type: categorical, choices: []}", "non-empty list"),
        ("train_freq: {type: categorical, choices: [[1, step]]}", "numbers, strings, booleans or null"),
    ],
)
def test_bad_search_spaces_are_refused(optuna, tmp_path, entry, message):
    from sb3_hgrn.experiments.tune import load_search_space

    path = write(tmp_path / "space.yml", f"soft_hgrn:\n  {entry}\n")
    with pytest.raises(ConfigError, match=message):
        load_search_space("soft_hgrn", path)


def test_search_space_without_the_preset_is_refused(optuna, tmp_path, capsys):
    path = write(tmp_path / "space.yml", SPACE)
    with pytest.raises(SystemExit) as exit_info:
        main(
            [
                "tune",
                *TOY[:2],
                "--preset",
                "dqn",
                "--search-space",
                str(path),
                "--folder",
                str(tmp_path / "t"),
            ]
        )
    assert exit_info.value.code == 2
    assert "has no search space for preset 'dqn' (it has: soft_hgrn)" in capsys.readouterr().err
    assert not (tmp_path / "t").exists()


def test_a_parameter_both_searched_and_fixed_is_refused(optuna, tmp_path):
    from sb3_hgrn.experiments.tune import TuneSetup, load_search_space

    space = load_search_space("soft_hgrn", write(tmp_path / "space.yml", SPACE))
    with pytest.raises(ConfigError, match="policy_kwargs.hidden_dim is both searched and fixed"):
        TuneSetup("surviving_v0", "soft_hgrn", "ci", 0, space, params={"policy_kwargs": {"hidden_dim": 8}})


# --- studies --------------------------------------------------------------------------------------


def stored_trials(optuna, folder: Path, study_name: str) -> list:
    storage = f"sqlite:///{folder / 'study.db'}"
    return optuna.load_study(study_name=study_name, storage=storage).get_trials()


def test_tune_then_train_with_the_best_config(optuna, tmp_path):
    space = write(tmp_path / "space.yml", SPACE)
    args = ["tune", *TOY, "--timesteps", "300", "--eval-freq", "150", "--eval-episodes", "1"]
    args += ["--n-trials", "3", "--n-jobs", "2", "--pruner", "none", "--search-space", str(space)]
    args += ["--verbose", "0"]
    args += ["--env-param", "n_agents=5", "--param", "learning_starts=50", "--folder", str(tmp_path / "tune")]
    assert main(args) == 0
    folder = tmp_path / "tune" / "surviving_v0_soft_hgrn_ci"
    trials = stored_trials(optuna, folder, "surviving_v0_soft_hgrn_ci")
    assert [trial.state for trial in trials] == [optuna.trial.TrialState.COMPLETE] * 3
    assert len({trial.params["learning_rate"] for trial in trials}) == 3  # the two workers sample apart
    assert all(sorted(trial.intermediate_values) == [150, 300] for trial in trials)
    assert all(trial.value == trial.intermediate_values[300] for trial in trials)
    rows = list(csv.DictReader((folder / "trials.csv").open()))
    assert [row["state"] for row in rows] == ["COMPLETE"] * 3
    assert [float(row["params_learning_rate"]) for row in rows] == [t.params["learning_rate"] for t in trials]
    assert (folder / "optimization_history.png").read_bytes()[:4] == b"\x89PNG"
    assert (folder / "param_importances.png").read_bytes()[:4] == b"\x89PNG"

    best = max(trials, key=lambda trial: trial.value)
    best_file = folder / "best.yml"
    assert best_file.read_text().startswith(f"# Best trial {best.number} ")
    assert yaml.safe_load(best_file.read_text()) == {
        "env_kwargs": {"n_agents": 5},
        "soft_hgrn": {
            "learning_rate": best.params["learning_rate"],
            "batch_size": best.params["batch_size"],
            "gamma": best.params["gamma"],
            "policy_kwargs": {"hidden_dim": best.params["policy_kwargs.hidden_dim"]},
            "learning_starts": 50,
        },
    }
    train = ["train", *TOY, "--timesteps", "100", "--verbose", "0", "--config", str(best_file)]
    assert main([*train, "--folder", str(tmp_path / "runs")]) == 0
    run = yaml.safe_load(
        (tmp_path / "runs" / "surviving_v0" / "soft_hgrn" / "seed_0" / "config.yml").read_text()
    )
    assert run["env_kwargs"]["n_agents"] == 5 and run["extra"]["n_agents"] == 5
    applied = run["extra"]["algorithm_kwargs"]
    assert (
        applied["learning_rate"] == best.params["learning_rate"] and applied["gamma"] == best.params["gamma"]
    )
    assert applied["batch_size"] == best.params["batch_size"] and applied["learning_starts"] == 50
    assert applied["policy_kwargs"]["hidden_dim"] == best.params["policy_kwargs.hidden_dim"]


def test_a_pruned_trial_is_recorded_and_a_second_run_joins_the_study(optuna, tmp_path):
    from sb3_hgrn.experiments.tune import TuneSetup, load_search_space, run_study

    class PruneTrialOne(optuna.pruners.BasePruner):
        """Prunes trial 1 at its first report, never another."""

        def prune(self, study, trial) -> bool:
            return trial.number == 1

    space = load_search_space("soft_hgrn", write(tmp_path / "space.yml", SPACE))
    setup = TuneSetup(
        "surviving_v0", "soft_hgrn", "ci", 0, space, timesteps=288, eval_freq=60, eval_episodes=1
    )
    run_study(setup, tmp_path, n_trials=2, study_name="s", pruner=PruneTrialOne())
    study = run_study(setup, tmp_path, n_trials=1, study_name="s", pruner=PruneTrialOne())
    trials = stored_trials(optuna, tmp_path, "s")
    assert len(study.trials) == 3
    state = optuna.trial.TrialState
    assert [trial.state for trial in trials] == [state.COMPLETE, state.PRUNED, state.COMPLETE]
    assert list(trials[1].intermediate_values) == [60]  # stopped at its first evaluation
    assert trials[1].user_attrs["agent_steps"] == 60 and trials[2].user_attrs["agent_steps"] == 288
    assert sorted(trials[0].intermediate_values) == [60, 120, 180, 240, 288]
    rows = list(csv.DictReader((tmp_path / "trials.csv").open()))
    assert [row["state"] for row in rows] == ["COMPLETE", "PRUNED", "COMPLETE"]

    longer = TuneSetup(
        "surviving_v0", "soft_hgrn", "ci", 0, space, timesteps=600, eval_freq=60, eval_episodes=1
    )
    with pytest.raises(ConfigError, match=r"created for another setup \(timesteps differ\)"):
        run_study(longer, tmp_path, n_trials=1, study_name="s")
    assert len(stored_trials(optuna, tmp_path, "s")) == 3


def test_pruners(optuna, tmp_path, capsys):
    from sb3_hgrn.experiments.tune import make_pruner

    median = make_pruner("median", n_startup_trials=3, n_warmup_steps=100)
    assert isinstance(median, optuna.pruners.MedianPruner)
    assert (median._n_startup_trials, median._n_warmup_steps) == (3, 100)
    assert isinstance(make_pruner("halving"), optuna.pruners.SuccessiveHalvingPruner)
    assert isinstance(make_pruner("none"), optuna.pruners.NopPruner)
    with pytest.raises(SystemExit):
        main(["tune", *TOY, "--pruner", "hyperband", "--folder", str(tmp_path / "t")])
    assert "Unknown pruner 'hyperband'; available: median, halving, none" in capsys.readouterr().err
    assert not (tmp_path / "t").exists()


# --- failing trials -------------------------------------------------------------------------------

DIVERGING = "1.0e+30"
"""A learning rate whose first gradient steps make the network's weights, and so its logits, NaN."""
DIVERGING_SPACE = f"soft_hgrn:\n  learning_rate: {{type: categorical, choices: [1.0e-3, {DIVERGING}]}}\n"
SMALL = {"timesteps": 300, "eval_freq": 150, "eval_episodes": 1}
SMALL_ARGS = ["--timesteps", "300", "--eval-freq", "150", "--eval-episodes", "1"]
FIXED = {"env_params": {"n_agents": 5}, "params": {"learning_starts": 50}}
NAN_ERROR = "ValueError: Cannot sample actions: the policy's logits are not finite"


def test_a_failing_trial_is_recorded_and_the_study_goes_on(optuna, tmp_path, caplog):
    from sb3_hgrn.experiments.tune import TuneSetup, default_storage, load_search_space, open_study, run_study

    space = load_search_space("soft_hgrn", write(tmp_path / "space.yml", DIVERGING_SPACE))
    setup = TuneSetup("surviving_v0", "soft_hgrn", "ci", 0, space, **SMALL, **FIXED)
    study = open_study(setup, default_storage(tmp_path), "s")
    for learning_rate in (1e30, 1e-3, 1e30):
        study.enqueue_trial({"learning_rate": learning_rate})
    study = run_study(setup, tmp_path, n_trials=3, study_name="s", pruner=optuna.pruners.NopPruner())
    state = optuna.trial.TrialState
    assert [trial.state for trial in study.trials] == [state.FAIL, state.COMPLETE, state.FAIL]
    assert study.best_trial.number == 1 and (tmp_path / "best.yml").exists()
    assert study.trials[0].user_attrs["error"].startswith(NAN_ERROR)
    rows = list(csv.DictReader((tmp_path / "trials.csv").open()))
    assert [row["state"] for row in rows] == ["FAIL", "COMPLETE", "FAIL"]
    assert rows[0]["error"].startswith(NAN_ERROR) and rows[1]["error"] == ""
    assert len(rows[2]["error"]) <= 300  # the first line of the message, not the whole tensor
    log = caplog.text  # Optuna's warnings
    assert "Trial 0 failed" in log and "Trial 2 failed" in log and "logits are not finite" in log


def test_a_study_whose_every_trial_fails_ends_with_an_error(optuna, tmp_path, capfd):
    space = write(
        tmp_path / "space.yml",
        f"soft_hgrn:\n  learning_rate: {{type: categorical, choices: [{DIVERGING}]}}\n",
    )
    args = ["tune", *TOY, *SMALL_ARGS, "--n-trials", "2", "--pruner", "none", "--search-space", str(space)]
    args += ["--verbose", "0", "--env-param", "n_agents=5", "--param", "learning_starts=50"]
    assert main([*args, "--folder", str(tmp_path / "tune"), "--study-name", "s"]) == 1
    message = capfd.readouterr().err
    assert "tune: Every trial of the study 's' failed (2 of 2); the last, trial 1" in message
    assert NAN_ERROR in message and str(tmp_path / "tune" / "s" / "trials.csv") in message
    rows = list(csv.DictReader((tmp_path / "tune" / "s" / "trials.csv").open()))
    assert [row["state"] for row in rows] == ["FAIL", "FAIL"]
