"""The ``sb3-hgrn`` command line: train / evaluate / render runs, configs, and the Table 1 sweep."""

import csv
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from PIL import Image

from sb3_hgrn import RandomGraphPolicy, SoftHGRN, evaluate_graph_policy, make_graph_vec_env
from sb3_hgrn.cli import main
from sb3_hgrn.common.vec_env import REGISTERED_ENVS
from sb3_hgrn.experiments.config import (
    BUDGETS,
    ConfigError,
    load_hyperparams,
    parse_assignments,
    random_policy_config,
    resolve_config,
)
from sb3_hgrn.experiments.paper import PAPER_TABLE1, TABLE1_ENVS
from sb3_hgrn.experiments.policy_evaluation import EpsilonRandomPolicy, evaluate_model
from sb3_hgrn.experiments.run_folder import read_eval
from sb3_hgrn.experiments.runs import evaluate_random_policy, evaluate_run, load_run, make_env
from sb3_hgrn.experiments.table1 import write_tables
from sb3_hgrn.presets import TABLE1, make_model

REPO = Path(__file__).resolve().parents[1]
TOY = ["--budget", "ci", "--verbose", "0", "--threads", "1"]


@pytest.fixture(scope="module")
def surviving_run(tmp_path_factory) -> Path:
    """A toy Surviving run (5 agents, 20-step episodes, 600 agent-steps) trained through ``main``."""
    root = tmp_path_factory.mktemp("runs")
    args = ["train", "--env", "surviving_v0", "--preset", "soft_hgrn", "--seed", "3", "--folder", str(root)]
    args += [*TOY, "--timesteps", "600", "--save-freq", "300"]
    args += ["--param", "batch_size=4", "policy_kwargs.hidden_dim=16", "--env-param", "n_agents=5"]
    assert main(args) == 0
    return root / "surviving_v0" / "soft_hgrn" / "seed_3"


def test_train_writes_the_run_folder(surviving_run):
    names = {path.name for path in surviving_run.iterdir()}
    assert {"config.yml", "model.zip", "eval.json", "team_returns.csv", "tensorboard", "checkpoints"} <= names
    assert list((surviving_run / "tensorboard").glob("*/events.out.tfevents.*"))
    assert sorted(p.name for p in (surviving_run / "checkpoints").iterdir()) == [
        "model_300_steps.zip",
        "model_600_steps.zip",
        "model_training_state_300_steps.pkl",
        "model_training_state_600_steps.pkl",
    ]

    config = yaml.safe_load((surviving_run / "config.yml").read_text())
    assert config["env"] == "surviving_v0" and config["preset"] == "soft_hgrn" and config["budget"] == "ci"
    assert config["seed"] == 3 and config["n_envs"] == 1 and config["total_timesteps"] == 600
    assert config["env_kwargs"]["n_agents"] == 5 and config["env_kwargs"]["max_cycles"] == 20
    assert config["extra"]["algorithm"] == "SoftHGRN" and config["extra"]["package_version"]
    assert config["extra"]["algorithm_kwargs"]["batch_size"] == 4

    lines = (surviving_run / "team_returns.csv").read_text().splitlines()
    metadata = json.loads(lines[0][1:])
    assert lines[0].startswith("#") and metadata["env_id"] == "surviving_v0" and metadata["n_agents"] == 5
    assert lines[1] == "r,l,t"
    rows = list(csv.DictReader(lines[1:]))
    assert len(rows) == 600 // 5 // 20  # team episodes of 20 steps of 5 agents
    assert all(int(row["l"]) == 20 and np.isfinite(float(row["r"])) for row in rows)
    assert [float(row["t"]) for row in rows] == sorted(float(row["t"]) for row in rows)

    results = json.loads((surviving_run / "eval.json").read_text())
    assert results["completed"] and results["n_episodes"] == 2 and len(results["returns"]) == 2
    assert results["mean"] == pytest.approx(np.mean(results["returns"]))
    assert results["std"] == pytest.approx(np.std(results["returns"]))
    assert results["deterministic"] is False and results["epsilon"] == 0.0
    assert results["agent_steps"] == 600 and results["env_steps"] == 120 and results["n_agents"] == 5
    assert results["wall_time_s"] >= results["train_time_s"] > 0 and results["train_cpu_s"] > 0
    assert results["epsilon_evaluations"]["0.3"]["n_episodes"] == 2


def test_overrides_reach_model_and_env(surviving_run):
    model = SoftHGRN.load(surviving_run / "model.zip")
    assert model.batch_size == 4 and model.policy_kwargs["hidden_dim"] == 16
    assert model.learning_starts == 120  # from the ci budget of the config file


def test_evaluate_and_render(surviving_run, tmp_path, capsys):
    assert main(["evaluate", str(surviving_run), "--episodes", "3", "--threads", "1"]) == 0
    assert "team return" in capsys.readouterr().out
    checkpoint = surviving_run / "checkpoints" / "model_300_steps.zip"
    assert main(["evaluate", str(checkpoint), "--episodes", "2", "--deterministic", "--epsilon", "0.3"]) == 0
    printed = capsys.readouterr().out
    assert "over 2 episodes (greedy actions, epsilon 0.3; acting: Polyak average of the Q-network)" in printed

    gif = tmp_path / "episode.gif"
    assert (
        main(["render", str(surviving_run / "model.zip"), "--out", str(gif), "--steps", "12", "--fps", "5"])
        == 0
    )
    with Image.open(gif) as image:
        assert image.n_frames >= 3  # Pillow merges identical consecutive frames


class ConstantPolicy:
    """Action 3 for every agent."""

    def predict(self, observation, state=None, episode_start=None, deterministic=False):
        return np.full(len(observation["obs"]), 3), state


def test_evaluation_counts_the_actions_taken(surviving_run, capsys):
    env = make_graph_vec_env("surviving_v0", n_envs=2, seed=0, env_kwargs={"n_agents": 5, "max_cycles": 20})
    assert evaluate_model(ConstantPolicy(), env, 2, True)["action_frequencies"] == [0.0, 0.0, 0.0, 1.0, 0.0]
    shares = evaluate_model(RandomGraphPolicy(env, seed=0), env, 4, False)["action_frequencies"]
    assert sum(shares) == pytest.approx(1.0) and min(shares) > 0.12  # 400 agent-steps, 0.2 each expected
    assert main(["evaluate", str(surviving_run), "--episodes", "2", "--actions", "--threads", "1"]) == 0
    printed = capsys.readouterr().out.splitlines()[-1]
    assert printed.startswith("actions (fraction of agent-steps): ")
    assert sum(float(item.split(": ")[1]) for item in printed.split("): ")[1].split(", ")) == pytest.approx(
        1, abs=0.01
    )


def test_train_refuses_a_completed_run_and_resumes_from_checkpoint(surviving_run, capsys):
    args = ["train", "--env", "surviving_v0", "--preset", "soft_hgrn", "--seed", "3"]
    args += ["--folder", str(surviving_run.parents[2]), *TOY, "--timesteps", "600", "--save-freq", "300"]
    args += ["--param", "batch_size=4", "policy_kwargs.hidden_dim=16", "--env-param", "n_agents=5"]
    with pytest.raises(SystemExit) as error:
        main(args)
    assert error.value.code == 2 and "already holds a completed run" in capsys.readouterr().err
    for name in ("eval.json", "model.zip", "checkpoints/model_600_steps.zip"):  # as if killed at 300
        (surviving_run / name).unlink()
    assert main([*args, "--verbose", "1"]) == 0
    assert "Resuming from" in capsys.readouterr().out
    results = json.loads((surviving_run / "eval.json").read_text())
    assert results["resumed_from"] == "model_300_steps.zip" and results["agent_steps"] == 600
    lines = (surviving_run / "team_returns.csv").read_text().splitlines()
    assert lines.count("r,l,t") == 1 and len(lines) == 2 + 6  # rewound to 300 steps, then appended


def test_epsilon_never_picks_invalid_actions_on_ctc(tmp_path):
    env = make_graph_vec_env(
        "ctc_v0", seed=0, env_kwargs=resolve_config("ctc_v0", "soft_hgrn", "ci").env_kwargs
    )
    model = SoftHGRN("GraphPolicy", env, learning_starts=0, seed=0)
    policy = EpsilonRandomPolicy(model, epsilon=1.0, seed=0)
    observations, chosen = env.reset(), []
    for _ in range(30):
        actions, _ = policy.predict(observations)
        mask = observations["action_mask"].astype(bool)
        assert mask[np.arange(len(actions)), actions].all()
        chosen.append(actions)
        observations, *_ = env.step(actions)
    assert len(np.unique(np.concatenate(chosen))) == env.action_space.n  # all valid actions occur

    args = [
        "train",
        "--env",
        "ctc_v0",
        "--preset",
        "dgn",
        "--folder",
        str(tmp_path),
        *TOY,
        "--timesteps",
        "400",
    ]
    assert main(args) == 0
    # the env raises on any action outside an agent's group: evaluation with epsilon 1 must not
    assert (
        main(["evaluate", str(tmp_path / "ctc_v0" / "dgn" / "seed_0"), "--episodes", "2", "--epsilon", "1"])
        == 0
    )


def test_parse_assignments():
    parsed = parse_assignments(["lr=1e-3", "policy_kwargs.hidden_dim=32", "policy_kwargs.recurrent=false"])
    assert parsed == {"lr": 1e-3, "policy_kwargs": {"hidden_dim": 32, "recurrent": False}}
    assert parse_assignments(["alpha_optimizer=sgd", "x={a: 1}", "y=[1, 2]"]) == {
        "alpha_optimizer": "sgd",
        "x": {"a": 1},
        "y": [1, 2],
    }
    for bad in (["batch_size"], ["=3"], ["a..b=1"]):
        with pytest.raises(ConfigError, match="Malformed"):
            parse_assignments(bad)


CI_TRAIN = ["train", "--budget", "ci", "--env", "surviving_v0"]
"""A train command that, were a bad argument let through, would train only the ci budget."""


@pytest.mark.parametrize(
    "args, message",
    [
        (["train", "--env", "nope_v0", "--preset", "dqn"], "Unknown env 'nope_v0'"),
        (["train", "--env", "surviving_v0", "--preset", "nope"], "Unknown preset 'nope'"),
        (["train", "--env", "surviving_v0", "--preset", "dqn", "--budget", "huge"], "Unknown budget 'huge'"),
        (["train", "--env", "surviving_v0", "--preset", "dqn", "--param", "batch_size"], "Malformed --param"),
        (
            ["train", "--env", "surviving_v0", "--preset", "dqn", "--param", "bogus=1"],
            "takes no argument 'bogus'",
        ),
        (["train", "--env", "surviving_v0", "--preset", "dqn", "--param", "seed=1"], "set by the runner"),
        (
            ["train", "--env", "surviving_v0", "--preset", "dqn", "--param", "alpha_optimizer=x"],
            "Cannot build preset",
        ),
        (["train", "--env", "surviving_v0", "--preset", "dqn", "--env-param", "n_agnts=3"], "Cannot build"),
        (
            [*CI_TRAIN, "--preset", "dqn", "--param", "policy_kwargs.hidden_dim=abc"],
            "policy_kwargs.hidden_dim must be an integer, got 'abc'",
        ),
        (
            [*CI_TRAIN, "--preset", "dqn", "--param", "policy_kwargs.recurrent=2"],
            "policy_kwargs.recurrent must be true or false, got 2",
        ),
        (
            [*CI_TRAIN, "--preset", "soft_hgrn", "--param", "hidden_dtype=float8"],
            "hidden_dtype must name a numpy float dtype",
        ),
        (
            [*CI_TRAIN, "--preset", "soft_hgrn", "--param", "learning_starts=abc"],
            "learning_starts must be an integer, got 'abc'",
        ),
        (
            [*CI_TRAIN, "--preset", "soft_hgrn", "--env-param", "n_agents=abc"],
            "n_agents must be an integer in 1..1024",
        ),
        (["reproduce", "table1", "--budget", "ci", "--envs", "nope_v0"], "Unknown env 'nope_v0'"),
        (["reproduce", "table1", "--budget", "nope"], "Unknown budget 'nope'"),
        (["evaluate", "/nonexistent/run"], "No run folder or model file"),
    ],
)
def test_bad_input_gives_clear_errors(args, message, tmp_path, capsys):
    with pytest.raises(SystemExit) as error:
        main([*args, "--folder", str(tmp_path)] if args[0] != "evaluate" else args)
    assert error.value.code == 2
    assert message in capsys.readouterr().err


def test_a_sweep_refuses_a_wrongly_typed_grid_value_before_training(tmp_path, capsys):
    with pytest.raises(SystemExit) as error:
        main(["sweep", "--env", "surviving_v0", "--budget", "ci", "--presets", "dqn", "--seeds", "1",
              "--timesteps", "50", "--grid", "policy_kwargs.n_heads=2,x",
              "--folder", str(tmp_path)])  # fmt: skip
    assert error.value.code == 2
    assert "policy_kwargs.n_heads must be an integer, got 'x'" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())


def test_a_config_file_with_a_wrongly_typed_argument_names_the_argument(tmp_path, capsys):
    config = tmp_path / "mine.yml"
    config.write_text("default:\n  policy_kwargs:\n    hidden_dim: wide\n")
    with pytest.raises(SystemExit) as error:
        main(["train", "--env", "surviving_v0", "--preset", "dqn", "--budget", "ci", "--config", str(config),
              "--folder", str(tmp_path)])  # fmt: skip
    assert error.value.code == 2
    assert "policy_kwargs.hidden_dim must be an integer, got 'wide'" in capsys.readouterr().err
    assert not (tmp_path / "surviving_v0").exists()


@pytest.mark.parametrize("command", ["evaluate", "render"])
def test_evaluate_and_render_name_a_bad_env_param(surviving_run, command, capsys):
    with pytest.raises(SystemExit) as error:
        main([command, str(surviving_run), "--env-param", "n_agents=0"])
    assert error.value.code == 2
    assert "n_agents must be an integer in 1..1024" in capsys.readouterr().err


def test_configs_define_every_budget_and_build_every_preset():
    for env in REGISTERED_ENVS:
        config = load_hyperparams(env)
        assert set(BUDGETS) <= set(config["budgets"])
        assert resolve_config(env, "soft_hgrn", "paper").paper
    for env in (*TABLE1_ENVS, "ctc_v0"):
        vec_env = None
        for preset in TABLE1:
            config = resolve_config(env, preset, "ci")
            vec_env = vec_env or make_env(config, config.n_envs, 0)
            model = make_model(preset, vec_env, paper=config.paper, seed=0, **config.hyperparams)
            assert model.learning_starts < config.total_timesteps
        vec_env.close()
    assert set(PAPER_TABLE1) == set(TABLE1)


def test_reproduce_table1_writes_tables_and_resumes(tmp_path):
    command = [sys.executable, "-m", "sb3_hgrn", "reproduce", "table1", "--budget", "ci", "--seeds", "1"]
    command += ["--presets", "dqn", "soft_hgrn", "--envs", "surviving_v0", "--folder", str(tmp_path)]
    command += ["--threads", "1"]
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    done = subprocess.run(command, capture_output=True, text=True, env=env, timeout=300)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "2 to run" in done.stdout

    rows = list(csv.DictReader((tmp_path / "table1.csv").open()))
    assert [(row["env"], row["preset"]) for row in rows] == [
        ("surviving_v0", "dqn"),
        ("surviving_v0", "soft_hgrn"),
        ("surviving_v0", "random"),  # the untrained anchor
    ]
    for row in rows:
        trained = row["preset"] != "random"
        assert row["seeds_done"] == "1" and row["eval_episodes"] == "2"
        assert row["agent_steps"] == ("1200" if trained else "0") and row["env_steps"] == (
            "200" if trained else "0"
        )
        assert float(row["wall_time_s"]) >= (0.01 if trained else 0.0) and row["mean"] != ""
        assert row["iqm"] == row["iqm_low"] == row["iqm_high"] == row["mean"]  # one seed: no spread
    table = (tmp_path / "table1.md").read_text()
    assert "budget `ci`" in table and "smaller than the paper's" in table and "| Soft-HGRN | " in table
    assert "194 +- 41" in table and "-7453 +- 74" in table  # the paper's figures beside ours
    random = f"{float(rows[2]['mean']):.1f}"
    assert f"| Random | {random} [{random}, {random}] | {random} | - |" in table
    assert "| 1,200 | 200 | 2 |" in table and "## Across envs" in table
    assert (tmp_path / "table1_aggregate.csv").exists() and (tmp_path / "table1_improvement.csv").exists()
    assert "Probability of improvement" not in table  # no ablation of Soft-HGRN and no CTC run here

    runs = tmp_path / "table1" / "surviving_v0"
    kept = (runs / "dqn" / "seed_0" / "eval.json").stat().st_mtime_ns
    anchor = (runs / "random" / "seed_0" / "eval.json").stat().st_mtime_ns
    (runs / "soft_hgrn" / "seed_0" / "eval.json").unlink()
    done = subprocess.run(command, capture_output=True, text=True, env=env, timeout=300)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "1 already done, 1 to run" in done.stdout and "soft_hgrn seed 0" in done.stdout
    assert "dqn seed 0" not in done.stdout.split("to run")[1]
    assert (runs / "dqn" / "seed_0" / "eval.json").stat().st_mtime_ns == kept
    assert (runs / "random" / "seed_0" / "eval.json").stat().st_mtime_ns == anchor
    assert (runs / "soft_hgrn" / "seed_0" / "eval.json").exists()

    rows = write_tables(tmp_path, "ci", ["surviving_v0"], ["dqn", "dgn"], [0, 1])
    assert rows[1]["mean"] is None and rows[0]["seeds_done"] == 1
    table = (tmp_path / "table1.md").read_text()
    assert "| DGN | - | - | -286 +- 67 |" in table and "(1/2)" in table


def test_random_anchor_follows_the_evaluation_protocol(tmp_path):
    config = random_policy_config("surviving_v0", "ci", seed=3)
    assert config.preset == "random" and config.total_timesteps == 0 and config.hyperparams == {}
    done = evaluate_random_policy(config, tmp_path / "anchor")
    assert read_eval(tmp_path / "anchor") == done
    assert done["n_episodes"] == config.eval_episodes and done["agent_steps"] == 0 and done["budget"] == "ci"

    # the same episodes as a trained run's evaluation: env copies seeded seed + 1000
    env = make_graph_vec_env(
        "surviving_v0", n_envs=config.eval_n_envs, seed=3 + 1000, env_kwargs=config.env_kwargs
    )
    returns, _ = evaluate_graph_policy(
        RandomGraphPolicy(env, seed=3), env, n_eval_episodes=config.eval_episodes, return_episode_rewards=True
    )
    assert done["returns"] == pytest.approx(returns)
    with pytest.raises(ConfigError, match="Unknown budget"):
        random_policy_config("surviving_v0", "nope")


def test_evaluate_online_acts_with_the_online_network_of_an_averaging_model(surviving_run, tmp_path):
    args = ["train", "--env", "surviving_v0", "--preset", "soft_hgrn", "--seed", "3", "--folder"]
    args += [str(tmp_path), *TOY, "--timesteps", "600", "--env-param", "n_agents=5", "--param"]
    args += ["batch_size=4", "policy_kwargs.hidden_dim=16", "policy_kwargs.average_tau=0.05"]
    assert main(args) == 0
    run = tmp_path / "surviving_v0" / "soft_hgrn" / "seed_3"
    by_network = {}
    for online in (False, True):
        model, env, _ = load_run(run, device="cpu")
        assert model.policy.q_net_average is not None
        if online:
            model.policy.drop_average()
        by_network[online] = evaluate_model(model, env, 4, True)
        assert evaluate_run(run, n_episodes=4, deterministic=True, online=online) == by_network[online]
    assert by_network[False] != by_network[True]
    online_only = tmp_path / "online_only"
    shutil.copytree(surviving_run, online_only)
    model, _, _ = load_run(online_only, device="cpu")
    model.policy.drop_average()
    model.save(online_only / "model.zip")
    with pytest.raises(ConfigError, match="--online needs a model that deploys an averaged network"):
        evaluate_run(online_only, n_episodes=1, online=True)


def test_evaluate_critic_acts_with_the_critics_boltzmann_policy(surviving_run, tmp_path):
    """``--critic`` evaluates a SAC-HGRN run with the policy ``behaviour_policy="critic"`` collects
    with; a model without an actor is refused, naming the flag."""
    args = ["train", "--env", "surviving_v0", "--preset", "sac_hgrn", "--seed", "3", "--folder"]
    args += [str(tmp_path), *TOY, "--timesteps", "600", "--env-param", "n_agents=5", "--param"]
    args += ["batch_size=4", "policy_kwargs.hidden_dim=16"]
    assert main(args) == 0
    run = tmp_path / "surviving_v0" / "sac_hgrn" / "seed_3"
    model, env, _ = load_run(run, device="cpu")
    model.policy.act = model.policy.critic_act
    by_critic = evaluate_model(model, env, 4, True)
    assert evaluate_run(run, n_episodes=4, deterministic=True, critic=True) == {
        **by_critic,
        "network": "online first critic (its Boltzmann policy)",
    }
    assert evaluate_run(run, n_episodes=4, deterministic=True) != by_critic
    with pytest.raises(ConfigError, match="--critic needs an actor-critic model"):
        evaluate_run(surviving_run, n_episodes=1, critic=True)
    with pytest.raises(ConfigError, match="--critic and --online"):
        evaluate_run(run, n_episodes=1, critic=True, online=True)


def test_evaluation_names_the_action_rule_it_used(surviving_run, tmp_path, capsys):
    """Greedy for DQN-style presets and deterministic flags, sampled for stochastic policies: in what
    ``evaluate`` prints and in ``eval.json``."""
    args = ["train", "--env", "surviving_v0", "--preset", "dqn", "--seed", "3", "--folder", str(tmp_path)]
    args += [*TOY, "--timesteps", "200", "--param", "batch_size=4", "--env-param", "n_agents=5"]
    assert main(args) == 0
    dqn_run = tmp_path / "surviving_v0" / "dqn" / "seed_3"
    dqn_results = json.loads((dqn_run / "eval.json").read_text())
    assert dqn_results["actions"] == "greedy" and dqn_results["deterministic"] is True
    assert dqn_results["epsilon_evaluations"]["0.3"]["actions"] == "greedy"
    soft_results = json.loads((surviving_run / "eval.json").read_text())
    assert soft_results["actions"] == "sampled" and soft_results["deterministic"] is False
    capsys.readouterr()
    for run, flags, rule in [
        (dqn_run, [], "greedy"),
        (surviving_run, [], "sampled"),
        (surviving_run, ["--deterministic"], "greedy"),
    ]:
        assert main(["evaluate", str(run), "--episodes", "1", "--threads", "1", *flags]) == 0
        printed = capsys.readouterr().out
        assert f"({rule} actions, epsilon 0; acting: Polyak average of the Q-network)" in printed
    env = make_graph_vec_env("surviving_v0", n_envs=1, seed=0, env_kwargs={"n_agents": 5, "max_cycles": 20})
    random_results = evaluate_model(RandomGraphPolicy(env, seed=0), env, 1, True)
    assert random_results["actions"] == "uniform random" and random_results["network"] is None
