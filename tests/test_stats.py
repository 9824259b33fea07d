"""Robust statistics (rliable) against hand-computed values, and Table 1's columns and files from them."""

import csv
import json
import re
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
from rliable import library

from sb3_hgrn.experiments.config import ConfigError
from sb3_hgrn.experiments.run_folder import figure_root, run_folder
from sb3_hgrn.experiments.stats import (
    INSTALL_COMMAND,
    improvement_interval,
    iqm,
    iqm_interval,
    normalise,
    performance_profiles,
    probability_of_improvement,
    run_fractions,
)
from sb3_hgrn.experiments.table1 import run_sweep, write_tables

REPS = 300
"""Bootstrap resamples in these tests (the tables use 2,000)."""


def test_iqm_trims_a_quarter_at_each_end() -> None:
    assert iqm(np.arange(8.0).reshape(-1, 1)) == pytest.approx(3.5)  # mean of 2, 3, 4, 5
    assert iqm(np.array([[1.0, 2.0], [3.0, 100.0]])) == pytest.approx(2.5)  # all tasks' runs together
    assert iqm(np.array([[1.0], [2.0], [10.0]])) == pytest.approx(13 / 3)  # under 4 runs: the mean


def test_iqm_interval_of_three_runs_spans_min_to_max() -> None:
    # every resample of 3 runs has probability 1 / 27 > 2.5 %, so the all-lowest and all-highest
    # resamples (means 1 and 10) are the 2.5 % and 97.5 % percentiles
    state = np.random.get_state()
    interval = iqm_interval(np.array([[1.0], [2.0], [10.0]]), REPS)
    assert (interval.estimate, interval.low, interval.high) == pytest.approx((13 / 3, 1.0, 10.0))
    assert iqm_interval(np.array([[1.0], [2.0], [10.0]]), REPS) == interval  # seeded: the same each time
    np.testing.assert_array_equal(np.random.get_state()[1], state[1])  # the global generator restored


def test_iqm_interval_contains_the_estimate() -> None:
    scores = np.array([[0.0, 1.0], [2.0, 5.0], [3.0, 4.0], [7.0, 6.0], [8.0, 90.0]])
    interval = iqm_interval(scores, REPS)
    assert interval.estimate == pytest.approx(4.5)  # 10 scores, 2 cut at each end: mean of 2..7 (mean 12.6)
    assert 2.0 < interval.low < 4.5 < interval.high < 90.0  # resamples with the outlier 3 times reach it
    np.random.seed(1)  # the bootstrap seeds the global generator itself: its state before does not matter
    assert iqm_interval(scores, REPS) == interval


def test_probability_of_improvement_by_hand() -> None:
    low, high = np.array([[0.0], [1.0], [2.0]]), np.array([[5.0], [6.0], [7.0]])
    assert probability_of_improvement(high, low) == 1.0 and probability_of_improvement(low, high) == 0.0
    assert probability_of_improvement(low, low.copy()) == 0.5
    # pairs (x, y): (1, 2) no, (1, 0) yes, (3, 2) yes, (3, 0) yes
    assert probability_of_improvement(np.array([[1.0], [3.0]]), np.array([[2.0], [0.0]])) == 0.75
    # a tie counts half: (1, 2) no, (1, 3) no, (2, 2) half, (2, 3) no
    assert probability_of_improvement(np.array([[1.0], [2.0]]), np.array([[2.0], [3.0]])) == 0.125
    # averaged over tasks: 1 on the first, 0.5 on the second
    assert probability_of_improvement(np.hstack([high, low]), np.hstack([low, low])) == 0.75


def test_improvement_interval_of_separated_and_identical_runs() -> None:
    low, high = np.array([[0.0], [1.0], [2.0]]), np.array([[5.0], [6.0], [7.0]])
    separated = improvement_interval(high, low, REPS)
    assert (separated.estimate, separated.low, separated.high) == (1.0, 1.0, 1.0)
    same = improvement_interval(low, low.copy(), REPS)
    assert same.estimate == 0.5 and same.low < 0.5 < same.high


def test_normalise_maps_low_to_zero_and_high_to_one() -> None:
    scores = np.array([[-10.0, 0.0], [20.0, 4.0], [5.0, 2.0]])
    np.testing.assert_allclose(
        normalise(scores, np.array([-10.0, 0.0]), np.array([20.0, 4.0])), [[0, 0], [1, 1], [0.5, 0.5]]
    )


def test_performance_profile_counts_runs_above_each_threshold() -> None:
    scores = np.array([[0.0, 0.5], [1.0, 2.0]])
    taus = np.array([-1.0, 0.5, 0.75, 1.5, 3.0])  # strictly above: the score 0.5 is not above 0.5
    np.testing.assert_allclose(run_fractions(scores, taus), [1.0, 0.5, 0.5, 0.25, 0.0])
    np.testing.assert_allclose(run_fractions(scores, taus), library.score_distributions(scores, taus))
    profile = performance_profiles({"a": scores}, taus, REPS)["a"]
    np.testing.assert_allclose(profile.fraction, [1.0, 0.5, 0.5, 0.25, 0.0])
    assert (profile.low <= profile.fraction).all() and (profile.fraction <= profile.high).all()
    assert profile.low[0] == profile.high[0] == 1.0 and profile.low[-1] == profile.high[-1] == 0.0


def test_missing_rliable_names_the_install_command(tmp_path, monkeypatch) -> None:
    monkeypatch.setitem(sys.modules, "rliable", None)
    with pytest.raises(ConfigError, match=re.escape(f"rliable package: {INSTALL_COMMAND}")):
        iqm(np.zeros((2, 1)))
    with pytest.raises(ConfigError, match="rliable"):  # before any run is trained
        run_sweep("ci", n_seeds=1, folder=tmp_path / "results", envs=["surviving_v0"], presets=["dqn"])
    assert not (tmp_path / "results").exists()


# --- Table 1 from a fake results folder ------------------------------------------------------------

SEED_SCORES = {
    # (env, preset): scores of seeds 0, 1, 2
    ("surviving_v0", "soft_hgrn"): [10.0, 20.0, 30.0],
    ("surviving_v0", "soft_hgrn-G"): [0.0, 5.0, 8.0],
    ("surviving_v0", "random"): [-10.0, -10.0, -10.0],
    ("surviving_v0", "dqn"): [0.0, 5.0, 10.0],  # the upper anchor, not among the compared presets
    ("pursuit_v0", "soft_hgrn"): [1.0, 2.0, 3.0],
    ("pursuit_v0", "soft_hgrn-G"): [1.0, 2.0, 3.0],
    ("pursuit_v0", "random"): [0.0, 0.0, 0.0],
    ("pursuit_v0", "dqn"): [0.5, 1.0, 1.5],
    ("ctc_v0", "hgn"): [5.0, 6.0, 7.0],
    ("ctc_v0", "dgn"): [1.0, 2.0, 3.0],
}


def write_eval(folder: Path, env: str, preset: str, seed: int, mean: float) -> None:
    """A complete ``eval.json`` of a ``ci`` run with team return ``mean``."""
    trained = preset != "random"
    done = {
        "completed": True,
        "env": env,
        "preset": preset,
        "budget": "ci",
        "seed": seed,
        "mean": mean,
        "std": 1.0,
        "n_episodes": 2,
        "n_agents": 5,
        "agent_steps": 1000 if trained else 0,
        "env_steps": 200 if trained else 0,
        "wall_time_s": 1.0,
    }
    folder.mkdir(parents=True)
    (folder / "eval.json").write_text(json.dumps(done))


def fake_results(folder: Path) -> Path:
    """``folder`` with the runs of :data:`SEED_SCORES` (CTC's where ``figure ctc`` keeps them)."""
    for (env, preset), scores in SEED_SCORES.items():
        root = figure_root(folder, "ctc") if env == "ctc_v0" else folder / "table1"
        for seed, score in enumerate(scores):
            write_eval(run_folder(root, env, preset, seed), env, preset, seed, score)
    return folder


@pytest.fixture(scope="module")
def results(tmp_path_factory) -> tuple[Path, list[dict]]:
    """The fake results folder with its tables (Surviving and Pursuit, Soft-HGRN and -G) and their rows."""
    folder = fake_results(tmp_path_factory.mktemp("results"))
    envs, presets = ["surviving_v0", "pursuit_v0"], ["soft_hgrn", "soft_hgrn-G"]
    return folder, write_tables(folder, "ci", envs, presets, [0, 1, 2], reps=REPS)


def read_csv(path: Path) -> list[dict[str, str]]:
    return list(csv.DictReader(path.open(encoding="utf-8")))


def test_table1_reports_iqm_intervals_beside_mean_and_std(results) -> None:
    results, rows = results
    cell = next(row for row in rows if (row["env"], row["preset"]) == ("surviving_v0", "soft_hgrn"))
    assert (cell["iqm"], cell["iqm_low"], cell["iqm_high"]) == pytest.approx((20.0, 10.0, 30.0))
    assert cell["mean"] == pytest.approx(20.0) and cell["std"] == pytest.approx(np.std([10, 20, 30]))
    written = read_csv(results / "table1.csv")[0]
    assert (written["iqm"], written["iqm_low"], written["iqm_high"], written["mean"]) == (
        "20.0",
        "10.0",
        "30.0",
        "20.0",
    )
    table = (results / "table1.md").read_text()
    assert "Surviving IQM [95 % CI] | mean +- std | paper |" in table
    assert "| Soft-HGRN | 20.0 [10.0, 30.0] | 20.0 +- 8.2 | 194 +- 41 |" in table


def test_table1_normalises_across_envs_between_random_and_the_fixed_reference(results) -> None:
    """The upper anchor is DQN's mean, not the best method's: the best method is not pulled to 1."""
    results, _ = results
    aggregate = {row["preset"]: row for row in read_csv(results / "table1_aggregate.csv")}
    # Surviving: (s + 10) / 15, Pursuit: s / 1. Soft-HGRN 1.33, 2, 2.67, 1, 2, 3: IQM of the middle 4 = 2
    assert float(aggregate["soft_hgrn"]["normalised_iqm"]) == pytest.approx(2.0)
    # Soft-HGRN -G: 0.67, 1, 1.2, 1, 2, 3: IQM of 1, 1, 1.2, 2 = 1.3
    assert float(aggregate["soft_hgrn-G"]["normalised_iqm"]) == pytest.approx(1.3)
    assert aggregate["soft_hgrn"]["runs_per_env"] == "3" and aggregate["soft_hgrn"]["envs"] == "2"
    assert "dqn" not in aggregate  # the reference anchors the scale; only the table's presets are rows
    low, high = (float(aggregate["soft_hgrn"][key]) for key in ("normalised_iqm_low", "normalised_iqm_high"))
    assert low < 2.0 < high
    table = (results / "table1.md").read_text()
    assert "Surviving: 0 = Random -10.0, 1 = DQN 5.0" in table and "| Soft-HGRN | 2.00 [" in table
    profile = read_csv(results / "table1_profile.csv")
    assert (results / "table1_profile.png").stat().st_size > 0 and {row["preset"] for row in profile} == {
        "soft_hgrn",
        "soft_hgrn-G",
    }
    first = next(row for row in profile if row["preset"] == "soft_hgrn")
    assert float(first["tau"]) == 0.0 and float(first["fraction"]) == 1.0  # every normalised score > 0


def test_without_a_reference_run_nothing_is_normalised(tmp_path) -> None:
    results = fake_results(tmp_path)
    shutil.rmtree(results / "table1" / "pursuit_v0" / "dqn")
    write_tables(results, "ci", ["surviving_v0", "pursuit_v0"], ["soft_hgrn"], [0, 1, 2], reps=REPS)
    aggregate = read_csv(results / "table1_aggregate.csv")
    assert [row["envs"] for row in aggregate] == ["1"]  # Pursuit, without DQN runs, is left out
    shutil.rmtree(results / "table1" / "surviving_v0" / "dqn")
    write_tables(results, "ci", ["surviving_v0", "pursuit_v0"], ["soft_hgrn"], [0, 1, 2], reps=REPS)
    assert "No env has a Random run and a DQN run above it" in (results / "table1.md").read_text()


def test_table1_reports_the_key_comparisons(results) -> None:
    results, _ = results
    comparisons = {
        (row["x"], row["y"], row["env"]): row for row in read_csv(results / "table1_improvement.csv")
    }
    assert set(comparisons) == {
        ("soft_hgrn", "soft_hgrn-G", "surviving_v0"),
        ("soft_hgrn", "soft_hgrn-G", "pursuit_v0"),
        ("soft_hgrn", "soft_hgrn-G", "all"),
        ("hgn", "dgn", "ctc_v0"),  # the only CTC pair with runs
    }
    separated = comparisons[("soft_hgrn", "soft_hgrn-G", "surviving_v0")]
    assert [separated[key] for key in ("probability", "probability_low", "probability_high")] == ["1.0"] * 3
    assert (
        float(comparisons[("soft_hgrn", "soft_hgrn-G", "pursuit_v0")]["probability"]) == 0.5
    )  # the same runs
    assert float(comparisons[("soft_hgrn", "soft_hgrn-G", "all")]["probability"]) == 0.75
    assert float(comparisons[("hgn", "dgn", "ctc_v0")]["probability"]) == 1.0
    table = (results / "table1.md").read_text()
    assert "| Soft-HGRN vs Soft-HGRN -G | 1.00 [1.00, 1.00] | 0.50 [" in table
    assert "| HGN vs DGN | 1.00 [1.00, 1.00] |" in table


def test_tables_during_a_sweep_leave_the_intervals_for_its_end(tmp_path) -> None:
    results = fake_results(tmp_path)
    rows = write_tables(results, "ci", ["surviving_v0"], ["soft_hgrn"], [0, 1, 2], robust=False)
    assert rows[0]["iqm"] is None and read_csv(results / "table1.csv")[0]["iqm"] == ""
    table = (results / "table1.md").read_text()
    assert "| Soft-HGRN | - | 20.0 +- 8.2 |" in table and "computed when the sweep ends" in table
    assert not (results / "table1_aggregate.csv").exists()
