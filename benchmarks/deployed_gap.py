"""Does the saved model keep what training showed? Its evaluation against its last training episodes.

Run: python benchmarks/deployed_gap.py FOLDER [FOLDER ...] [--fraction 0.1]

Reads every finished run folder under the given folders (those of ``sb3-hgrn train``, ``sweep`` or
``reproduce``: a ``team_returns.csv`` of training team episodes and an ``eval.json``) and prints one
line per run: the mean and standard deviation of the last ``--fraction`` of its training team
episodes (as the library logs them: the policy that collected, DQN-style presets with their
epsilon), the saved model's evaluation (its plain policy: sampled actions, greedy for DQN-style
presets), the gap between the two and whether the evaluation stays within one standard deviation
of the training mean. A summary line per folder, env and preset follows.
"""

from __future__ import annotations

import argparse
import json
from collections import defaultdict
from pathlib import Path

import numpy as np


def training_tail(csv_path: Path, fraction: float) -> tuple[float, float, int]:
    """Mean, standard deviation and count of the last ``fraction`` of a run's training team returns."""
    lines = csv_path.read_text(encoding="utf-8").splitlines()
    returns = np.array([float(line.split(",")[0]) for line in lines[2:] if line])
    tail = returns[-max(1, int(round(fraction * len(returns)))) :]
    return float(tail.mean()), float(tail.std()), len(tail)


def run_folders(root: Path) -> list[Path]:
    """Every folder under ``root`` holding a finished run."""
    return sorted(
        path.parent for path in root.rglob("eval.json") if (path.parent / "team_returns.csv").exists()
    )


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("folders", nargs="+", type=Path)
    parser.add_argument("--fraction", type=float, default=0.1, help="share of the last training episodes")
    args = parser.parse_args()
    groups: dict[tuple[str, ...], list[tuple[float, bool]]] = defaultdict(list)
    print("| run | training tail (mean +- std, episodes) | saved model | gap | kept |")
    print("|---|---|---|---|---|")
    for root in args.folders:
        for folder in run_folders(root):
            mean, std, count = training_tail(folder / "team_returns.csv", args.fraction)
            evaluation = json.loads((folder / "eval.json").read_text(encoding="utf-8"))["mean"]
            kept = evaluation >= mean - std
            groups[folder.parent.relative_to(root).parts].append((evaluation - mean, kept))
            print(
                f"| {folder.relative_to(root)} | {mean:.1f} +- {std:.1f} ({count}) | {evaluation:.1f} "
                f"| {evaluation - mean:+.1f} | {'yes' if kept else 'NO'} |"
            )
    print("\n| point / env / preset | mean gap | runs kept |")
    print("|---|---|---|")
    for key, values in groups.items():
        gaps, kept = zip(*values, strict=True)
        print(f"| {'/'.join(key)} | {np.mean(gaps):+.1f} | {sum(kept)} of {len(kept)} |")


if __name__ == "__main__":
    main()
