"""``--env MODULE:ATTR``: training, evaluating and sweeping an env of one's own from the command line."""

import json
import shutil
from pathlib import Path

import pytest
import yaml

from sb3_hgrn import make_graph_vec_env
from sb3_hgrn.cli import main
from sb3_hgrn.common.saved_controllers import ModelController
from sb3_hgrn.experiments.config import (
    REQUIRED_BUDGET_FIELDS,
    ConfigError,
    budget_settings,
    env_folder_name,
    resolve_config,
)
from sb3_hgrn.experiments.runs import make_env
from sb3_hgrn.experiments.sweep import SweepSettings, check_points, grid_points, plan_sweep
from tests.user_env_pkg import make_driven_env

SPEC = "tests.user_env_pkg:make_env"
FOLDER_NAME = "tests.user_env_pkg-make_env"
TOY = ["--budget", "ci", "--verbose", "0", "--threads", "1"]
CONFIG = {
    "default": {
        "learning_starts": 30,
        "batch_size": 4,
        "buffer_size": 500,
        "policy_kwargs": {"hidden_dim": 16},
    },
    "budgets": {
        "ci": {
            "n_envs": 1,
            "total_timesteps": 150,
            "eval_episodes": 2,
            "env_kwargs": {"n_agents": 3, "max_cycles": 5},
        }
    },
}


@pytest.fixture(scope="module")
def config_file(tmp_path_factory) -> Path:
    """A config file for the user env: the ci budget only (3 agents, 5-step episodes, 150 agent-steps)."""
    path = tmp_path_factory.mktemp("config") / "my_config.yml"
    path.write_text(yaml.safe_dump(CONFIG))
    return path


@pytest.fixture(scope="module")
def user_run(tmp_path_factory, config_file) -> Path:
    """A run of the user env trained through ``main``."""
    root = tmp_path_factory.mktemp("runs")
    args = ["train", "--env", SPEC, "--config", str(config_file), "--preset", "soft_hgrn"]
    assert main([*args, "--folder", str(root), *TOY]) == 0
    return root / FOLDER_NAME / "soft_hgrn" / "seed_0"


def exit_message(capsys, argv: list[str]) -> str:
    """The error message of ``main(argv)``, which must exit with status 2."""
    with pytest.raises(SystemExit) as error:
        main(argv)
    assert error.value.code == 2
    return capsys.readouterr().err


def test_train_writes_the_run_folder_of_a_user_env(user_run):
    config = yaml.safe_load((user_run / "config.yml").read_text())
    assert config["env"] == SPEC and config["env_kwargs"] == {"n_agents": 3, "max_cycles": 5}
    assert config["total_timesteps"] == 150 and config["extra"]["n_agents"] == 3
    results = json.loads((user_run / "eval.json").read_text())
    assert results["completed"] and results["env"] == SPEC and results["n_episodes"] == 2
    assert results["agent_steps"] >= 150 and results["lengths"] == [5, 5]


def test_evaluate_imports_the_user_env_its_user_names(user_run, capsys):
    assert main(["evaluate", str(user_run), "--env", SPEC, "--episodes", "2", "--threads", "1"]) == 0
    assert "team return" in capsys.readouterr().out
    assert main(["evaluate", str(user_run), "--trust-config", "--episodes", "1", "--threads", "1"]) == 0


def test_evaluate_refuses_a_user_env_only_the_run_folder_names(user_run, tmp_path, capsys):
    copy = tmp_path / "copy"
    shutil.copytree(user_run, copy)
    config = yaml.safe_load((copy / "config.yml").read_text())
    config["env"] = "tests.never_imported:make_env"  # no such module: refused before any import
    (copy / "config.yml").write_text(yaml.safe_dump(config))
    for command in (["evaluate", str(copy)], ["render", str(copy), "--out", str(tmp_path / "x.gif")]):
        message = exit_message(capsys, command)
        assert "names the env 'tests.never_imported:make_env'" in message and "--trust-config" in message
        assert "Cannot import" not in message
    message = exit_message(capsys, ["evaluate", str(copy), "--env", SPEC])
    assert "was trained on tests.never_imported:make_env" in message
    message = exit_message(capsys, ["evaluate", str(copy), "--trust-config"])
    assert "Cannot import module 'tests.never_imported'" in message


@pytest.mark.parametrize(
    ("spec", "expected"),
    [
        ("tests.no_such_module:make_env", "Cannot import module 'tests.no_such_module'"),
        ("tests.user_env_pkg:missing", "Module 'tests.user_env_pkg' has no attribute 'missing'"),
        ("tests.user_env_pkg:NOT_A_FACTORY", "tests.user_env_pkg.NOT_A_FACTORY (the env"),
        ("tests.user_env_pkg:", "Malformed env 'tests.user_env_pkg:'"),
        ("tests..user_env_pkg:make_env", "Malformed env"),
        ("tests.user_env_pkg:make_env:x", "Malformed env"),
    ],
)
def test_bad_env_specs_exit_with_status_2(spec, expected, config_file, tmp_path, capsys):
    args = ["train", "--env", spec, "--config", str(config_file), "--preset", "soft_hgrn"]
    message = exit_message(capsys, [*args, "--folder", str(tmp_path), *TOY])
    assert expected in message
    assert not any(tmp_path.iterdir())  # refused before any run folder is made


def test_a_user_env_needs_a_config_with_its_budget(config_file, tmp_path, capsys):
    args = ["train", "--env", SPEC, "--preset", "soft_hgrn", "--folder", str(tmp_path), *TOY]
    message = exit_message(capsys, args)
    assert "--config FILE (it has none)" in message and "n_envs, total_timesteps, eval_episodes" in message
    assert "budgets:\n  ci:\n    n_envs: 1" in message  # the minimal example, for the chosen budget
    message = exit_message(capsys, [*args[:-6], "--config", str(config_file), "--budget", "cpu"])
    assert "budget 'cpu'" in message and "missing: n_envs, total_timesteps, eval_episodes" in message
    partial = tmp_path / "partial.yml"
    partial.write_text(yaml.safe_dump({"budgets": {"ci": {"n_envs": 1, "total_timesteps": 100}}}))
    with pytest.raises(ConfigError, match="missing: eval_episodes$|missing: eval_episodes\\."):
        resolve_config(SPEC, "soft_hgrn", "ci", config_file=partial)
    extra = tmp_path / "extra.yml"
    extra.write_text(yaml.safe_dump({"budgets": {"ci": {"eval_episodes": 3}}}))
    assert resolve_config(SPEC, "soft_hgrn", "ci", config_file=[partial, extra]).eval_episodes == 3
    assert set(REQUIRED_BUDGET_FIELDS) <= set(budget_settings(SPEC, "ci", [partial, extra]))


@pytest.mark.parametrize(
    "text, message",
    [
        (
            "default: {policy_kwargs: {hidden_dim: abc}}",
            "{file}: default.policy_kwargs.hidden_dim must be an integer, got 'abc' (SoftHGRN, preset "
            "'soft_hgrn').",
        ),
        (
            "budgets: {ci: {soft_hgrn: {learning_starts: 1.5}}}",
            "{file}: budgets.ci.soft_hgrn.learning_starts must be an integer, got 1.5",
        ),
        (
            "soft_hgrn: {bogus: 1}",
            "{file}: soft_hgrn: SoftHGRN (preset 'soft_hgrn') takes no argument 'bogus'",
        ),
        ("budgets: {ci: {paper: 'no'}}", "{file} budget ci: paper must be true or false, got 'no'."),
        (
            "budgets: {ci: {eval_n_envs: 2.0}}",
            "{file} budget ci: eval_n_envs must be a positive integer, got 2.0.",
        ),
        ("budgets: {ci: {n_envs: true}}", "{file} budget ci: n_envs must be a positive integer, got True."),
        (
            "budgets: {ci: {eval_epsilons: [0.3, x]}}",
            "{file} budget ci: eval_epsilons must be a list of numbers in [0, 1], got [0.3, 'x'].",
        ),
    ],
)
def test_a_wrongly_typed_value_names_the_config_file_it_is_in(text, message, config_file, tmp_path):
    """Each file's values are checked before they are merged, so the message names the file (here the
    second of two) and the value's place in it."""
    second = tmp_path / "second.yml"
    second.write_text(text)
    with pytest.raises(ConfigError) as error:
        resolve_config(SPEC, "soft_hgrn", "ci", config_file=[config_file, second])
    assert message.format(file=second) in str(error.value)


def test_a_pettingzoo_style_module_attribute_is_an_env(config_file):
    config = resolve_config("sb3_hgrn.envs:surviving_v0", "soft_hgrn", "ci", config_file=config_file)
    config.env_kwargs = {"n_agents": 4, "map_size": 8}
    env = make_env(config, 2, seed=0)
    assert env.n_agents == 4 and env.num_envs == 8
    env.close()


def test_run_folder_names_of_user_envs():
    assert env_folder_name("surviving_v0") == "surviving_v0"
    assert env_folder_name("my_package.my_module:make_env") == "my_package.my_module-make_env"
    with pytest.raises(ConfigError, match="Malformed env '../x:y'"):
        env_folder_name("../x:y")


def test_a_sweep_of_a_user_env_passes_its_config_to_every_run(config_file, tmp_path):
    settings = SweepSettings(SPEC, "ci", params={"batch_size": 8}, config=[str(config_file)])
    points = grid_points({"learning_rate": [1e-3, 3e-4]}, {})
    check_points(settings, points, ["soft_hgrn"])
    jobs = plan_sweep(tmp_path, settings, points, ["soft_hgrn"], [0])
    assert [job.folder.relative_to(tmp_path).parts[1] for job in jobs] == [FOLDER_NAME] * 2
    for job in jobs:
        at = job.args.index("--config")
        assert job.args[at + 1] == str(config_file) and job.args[at + 2] == "--param"
    assert "config" not in SweepSettings("surviving_v0", "ci").record()  # old sweep.yml files still match
    with pytest.raises(ConfigError, match="--config FILE"):
        check_points(SweepSettings(SPEC, "ci"), points, ["soft_hgrn"])


def test_a_study_of_a_user_env_is_named_as_its_run_folders(config_file):
    tune = pytest.importorskip("sb3_hgrn.experiments.tune", exc_type=ImportError)
    setup = tune.TuneSetup(SPEC, "soft_hgrn", "ci", 0, {}, config=[str(config_file)])
    assert setup.default_study_name() == f"{FOLDER_NAME}_soft_hgrn_ci"
    assert setup.run_config({"learning_rate": 1e-3}).env_kwargs == {"n_agents": 3, "max_cycles": 5}
    assert setup.describe()["config"] == [str(config_file)]
    assert "config" not in tune.TuneSetup("surviving_v0", "soft_hgrn", "ci", 0, {}).describe()
    with pytest.raises(ConfigError, match="--config FILE"):
        tune.TuneSetup(SPEC, "soft_hgrn", "ci", 0, {})


DRIVEN_SPEC = "tests.user_env_pkg:make_driven_env"
DRIVEN_FOLDER = "tests.user_env_pkg-make_driven_env"


def train_driven(config_file: Path, root: Path, seed: int, *extra: str) -> Path:
    """Train a run of the user env whose other half a controller drives; its folder."""
    args = ["train", "--env", DRIVEN_SPEC, "--config", str(config_file), "--preset", "soft_hgrn"]
    assert main([*args, "--folder", str(root), "--seed", str(seed), *TOY, *extra]) == 0
    return root / DRIVEN_FOLDER / "soft_hgrn" / f"seed_{seed}"


def test_a_saved_model_given_by_path_drives_the_other_agents_of_a_user_env(tmp_path, capsys):
    config_file = tmp_path / "driven.yml"
    config = {**CONFIG, "budgets": {"ci": {**CONFIG["budgets"]["ci"], "env_kwargs": {"max_cycles": 5}}}}
    config_file.write_text(yaml.safe_dump(config))
    first = train_driven(config_file, tmp_path / "runs", 0)
    model_path = str(first / "model.zip")

    # make_graph_vec_env loads the path the module's model_paths names, once for all copies
    vec_env = make_graph_vec_env(make_driven_env, n_envs=2, env_kwargs={"controller": model_path})
    controllers = [env.env.controller for env in vec_env.envs]
    assert isinstance(controllers[0], ModelController) and controllers[0] is controllers[1]
    assert controllers[0].model.policy.n_agents == 3 and vec_env.num_envs == 6
    with pytest.raises(ValueError, match="loads no saved model"):
        make_driven_env(controller=model_path)  # the env side loads nothing

    # the command line trains against it, and a run whose config names it outside its folder
    second = train_driven(config_file, tmp_path / "runs", 1, "--env-param", f"controller={model_path}")
    assert yaml.safe_load((second / "config.yml").read_text())["env_kwargs"]["controller"] == model_path
    message = exit_message(capsys, ["evaluate", str(second), "--env", DRIVEN_SPEC, "--episodes", "1"])
    assert f"sets controller='{model_path}', a model outside the run folder" in message
    given = ["--env-param", f"controller={model_path}", "--episodes", "1", "--threads", "1"]
    assert main(["evaluate", str(second), "--env", DRIVEN_SPEC, *given]) == 0
