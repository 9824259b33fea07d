"""``sb3-hgrn figure``: every figure at budget ci draws a PNG with its data, finished runs are skipped."""

import contextlib
import csv
import io
import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from sb3_hgrn.cli import main
from sb3_hgrn.experiments.figures import FIGURES, mean_band, moving_average, transfer_counts

FIGURE_ARGS = {
    "ctc": ["--seeds", "2", "--presets", "hgn", "dgn", "--jobs", "2"],  # 2 seeds: error bands
    "alpha": ["--seeds", "1"],
    "transfer": ["--seeds", "1", "--presets", "soft_hgrn"],
    "p_alpha": ["--seeds", "1", "--ratios", "0.1", "0.5"],
}


def run_figure(name: str, folder: Path) -> tuple[int, str]:
    """``sb3-hgrn figure NAME --budget ci`` into ``folder``: exit status and printed output."""
    args = ["figure", name, "--budget", "ci", "--folder", str(folder), "--threads", "1", *FIGURE_ARGS[name]]
    output = io.StringIO()
    with contextlib.redirect_stdout(output):
        status = main(args)
    return status, output.getvalue()


@pytest.fixture(scope="module")
def drawn(tmp_path_factory) -> tuple[Path, dict[str, str]]:
    """Every figure drawn once at budget ci: the results folder and each command's output."""
    folder = tmp_path_factory.mktemp("results")
    outputs = {}
    for name in FIGURES:
        status, outputs[name] = run_figure(name, folder)
        assert status == 0, outputs[name]
    return folder, outputs


def read_rows(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as file:
        return list(csv.DictReader(file))


@pytest.mark.parametrize("name", list(FIGURES))
def test_figure_writes_png_data_and_summary(drawn, name):
    folder, outputs = drawn
    png = folder / "figures" / f"{name}.png"
    with Image.open(png) as image:
        assert image.width > 400 and image.height > 300
    rows = read_rows(png.with_suffix(".csv"))
    info = json.loads(png.with_suffix(".json").read_text())
    assert rows and info["figure"] == name and info["budget"] == "ci"
    assert info["command"].startswith(f"sb3-hgrn figure {name} --budget ci")
    assert info["agent_steps"] > 0 and info["runs_done"] == info["runs_planned"] and info["wall_time_s"] >= 0
    assert info["description"] and info["seeds_done"] == list(range(int(FIGURE_ARGS[name][1])))
    for line in ("command: sb3-hgrn figure", "budget ci:", "agent-steps", "seeds:", "wall time:"):
        assert line in outputs[name]


def test_ctc_curves_have_both_twins_and_bands(drawn):
    rows = read_rows(drawn[0] / "figures" / "ctc.csv")
    assert {row["preset"] for row in rows} == {"hgn", "dgn"}
    assert {row["n_seeds"] for row in rows} == {"2"} and any(float(row["std"]) > 0 for row in rows)
    steps = [int(row["agent_steps"]) for row in rows if row["preset"] == "hgn"]
    assert steps == sorted(steps) and steps[-1] <= 1600  # the ci budget's agent-steps


def test_alpha_reads_every_tensorboard_series(drawn):
    rows = read_rows(drawn[0] / "figures" / "alpha.csv")
    series = {"alpha", "alpha_grad", "entropy", "target_entropy"}
    assert {row["series"] for row in rows if row["preset"] in ("soft_hgrn", "sac_hgrn")} == series
    assert {row["preset"] for row in rows} == {"soft_hgrn", "sac_hgrn"}
    target = {round(float(row["mean"]), 4) for row in rows if row["series"] == "target_entropy"}
    assert target == {round(0.2 * np.log(5), 4)}  # Soft-HGRN's default p_alpha


def test_transfer_and_p_alpha_points(drawn):
    rows = read_rows(drawn[0] / "figures" / "transfer.csv")
    assert [int(row["n_agents"]) for row in rows] == [2, 3, 6, 12, 24]  # 0.25x to 4x the trained 6
    assert {row["trained_agents"] for row in rows} == {"6"}
    rows = read_rows(drawn[0] / "figures" / "p_alpha.csv")
    assert [float(row["target_entropy_ratio"]) for row in rows] == [0.1, 0.5]


def test_drawing_again_skips_finished_runs(drawn):
    folder = drawn[0]
    runs = sorted((folder / "figures" / "ctc").glob("ctc_v0/*/seed_*/eval.json"))
    transfer = next((folder / "table1").glob("surviving_v0/*/seed_0/transfer.json"))  # Table 1's runs
    before = [path.stat().st_mtime_ns for path in [*runs, transfer]]
    for name in ("ctc", "transfer"):
        status, output = run_figure(name, folder)
        assert status == 0 and "already done, 0 to run" in output
    assert len(runs) == 4 and [path.stat().st_mtime_ns for path in [*runs, transfer]] == before


@pytest.mark.parametrize(
    "args, message",
    [
        (["nope"], "Unknown figure 'nope'; available: ctc, alpha, transfer, p_alpha"),
        (["ctc", "--budget", "huge"], "Unknown budget 'huge'"),
        (["alpha", "--presets", "dqn"], "needs a preset with a learned alpha"),
        (["ctc", "--ratios", "0.1"], "--ratios applies to the p_alpha figure only"),
        (["p_alpha", "--ratios", "1.5"], "must lie in [0, 1]"),
    ],
)
def test_bad_input_gives_clear_errors(args, message, tmp_path, capsys):
    with pytest.raises(SystemExit) as error:
        main(["figure", *args, "--folder", str(tmp_path)])
    assert error.value.code == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "figures").exists()


def test_curve_helpers():
    np.testing.assert_allclose(moving_average(np.array([1.0, 3.0, 5.0, 7.0]), 2), [1.0, 2.0, 4.0, 6.0])
    curves = [
        (np.array([0.0, 10.0, 20.0]), np.array([0.0, 1.0, 2.0])),
        (np.array([5.0, 20.0]), np.array([1.0, 4.0])),
    ]
    grid, mean, std = mean_band(curves)
    np.testing.assert_allclose(grid, [5.0, 12.5, 20.0])
    np.testing.assert_allclose(mean, [(0.5 + 1.0) / 2, (1.25 + 2.5) / 2, 3.0])
    np.testing.assert_allclose(std, [0.25, 0.625, 1.0])
    assert transfer_counts(100) == [25, 50, 100, 200, 400]  # the paper's
    assert transfer_counts(20) == [5, 10, 20, 40, 80]  # budget cpu
