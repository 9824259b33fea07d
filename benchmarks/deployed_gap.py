"""Does the saved model keep what training showed? Its evaluation against its last training episodes.

Run: python benchmarks/deployed_gap.py FOLDER [FOLDER ...] [--fraction 0.1] [--online-episodes N]
     [--greedy-episodes N] [--env MODULE:ATTR]

Reads every finished run folder under the given folders (those of ``sb3-hgrn train``, ``sweep`` or
``reproduce``: a ``team_returns.csv`` of training team episodes and an ``eval.json``) and prints one
line per run: the mean and standard deviation of the last ``--fraction`` of its training team
episodes (as the library logs them: the policy that collected, DQN-style presets with their
epsilon), the saved model's evaluation (its plain policy: sampled actions, greedy for DQN-style
presets), the gap between the two and whether the evaluation stays within one standard deviation
of the training mean. A summary line per folder, env and preset follows.

With ``--online-episodes N``, runs whose model deploys a Polyak average (``policy_kwargs.average_tau``)
are also evaluated with their online network over N episodes on the same env seeds as their final
evaluation (``sb3-hgrn evaluate RUN --online``): the same training run, deployed either way.

With ``--greedy-episodes N`` the saved model is evaluated twice more over N episodes on those env
seeds, with its sampled actions and with greedy ones (``sb3-hgrn evaluate RUN --deterministic``): the
same network under either action rule (for DQN-style presets, whose plain policy is greedy already,
both are greedy). Runs of an env of one's own need ``--env`` naming it (as ``sb3-hgrn evaluate
--env``).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np
import torch as th

from sb3_hgrn.experiments.policy_evaluation import evaluate_model
from sb3_hgrn.experiments.runs import EVAL_SEED_OFFSET, load_run

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # examples.<env>:make_env of one's own runs


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


def online_evaluation(folder: Path, n_episodes: int, env: str | None) -> float | None:
    """Mean team return of a run's online network over ``n_episodes`` on the env seeds of its final
    evaluation (``None`` when the model deploys its online network already)."""
    model, vec_env, _ = load_run(folder, env=env, device="cpu")
    try:
        if model.policy.average_network is None:
            return None
        model.policy.drop_average()
        return evaluate_model(model, vec_env, n_episodes, deterministic=False)["mean"]
    finally:
        vec_env.close()


def action_rule_evaluations(folder: Path, n_episodes: int, env: str | None) -> tuple[float, float]:
    """Mean team returns of a run's saved model with sampled and with greedy actions, ``n_episodes``
    each, both from the env seeds of its final evaluation."""
    model, vec_env, config = load_run(folder, env=env, device="cpu")
    means = []
    try:
        for deterministic in (False, True):
            vec_env.seed(config.seed + EVAL_SEED_OFFSET)  # both rules from the same env seeds
            means.append(evaluate_model(model, vec_env, n_episodes, deterministic=deterministic)["mean"])
    finally:
        vec_env.close()
    return means[0], means[1]


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("folders", nargs="+", type=Path)
    parser.add_argument("--fraction", type=float, default=0.1, help="share of the last training episodes")
    parser.add_argument("--online-episodes", type=int, default=0, help="also evaluate the online network")
    parser.add_argument(
        "--greedy-episodes", type=int, default=0, help="also evaluate sampled against greedy actions"
    )
    parser.add_argument("--env", help="the MODULE:ATTR env of runs of an env of one's own")
    args = parser.parse_args()
    th.set_num_threads(1)
    groups: dict[tuple[str, ...], list[tuple[float, bool]]] = defaultdict(list)
    online_groups: dict[tuple[str, ...], list[tuple[float, bool]]] = defaultdict(list)
    rule_groups: dict[tuple[str, ...], list[tuple[float, float]]] = defaultdict(list)
    print(
        "| run | training tail (mean +- std, episodes) | saved model | gap | kept | online network | kept "
        "| sampled | greedy |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    common = Path(os.path.commonpath([Path(folder).resolve() for folder in args.folders]))
    for root in args.folders:
        # several folders: each run is named with where its folder differs first, as their layouts may match
        prefix = Path(root).resolve().relative_to(common).parts if len(args.folders) > 1 else ()
        for folder in run_folders(root):
            mean, std, count = training_tail(folder / "team_returns.csv", args.fraction)
            evaluation = json.loads((folder / "eval.json").read_text(encoding="utf-8"))["mean"]
            kept = evaluation >= mean - std
            key = (*prefix, *folder.parent.relative_to(root).parts)
            groups[key].append((evaluation - mean, kept))
            online = "- | -"
            value = (
                online_evaluation(folder, args.online_episodes, args.env) if args.online_episodes else None
            )
            if value is not None:
                online_groups[key].append((value - mean, value >= mean - std))
                online = f"{value:.1f} | {'yes' if value >= mean - std else 'NO'}"
            rules = "- | -"
            if args.greedy_episodes:
                sampled, greedy = action_rule_evaluations(folder, args.greedy_episodes, args.env)
                rule_groups[key].append((sampled, greedy))
                rules = f"{sampled:.1f} | {greedy:.1f}"
            print(
                f"| {Path(*prefix, folder.relative_to(root))} | {mean:.1f} +- {std:.1f} ({count}) "
                f"| {evaluation:.1f} | {evaluation - mean:+.1f} | {'yes' if kept else 'NO'} | {online} "
                f"| {rules} |",
                flush=True,
            )
    print("\n| point / env / preset | deployed | mean gap | runs kept |")
    print("|---|---|---|---|")
    for label, table in (("saved model", groups), ("online network", online_groups)):
        for key, values in table.items():
            gaps, kept = zip(*values, strict=True)
            print(f"| {'/'.join(key)} | {label} | {np.mean(gaps):+.1f} | {sum(kept)} of {len(kept)} |")
    if rule_groups:
        print("\n| point / env / preset | sampled (mean) | greedy (mean) | greedy - sampled | greedy ahead |")
        print("|---|---|---|---|---|")
        for key, values in rule_groups.items():
            sampled, greedy = (np.array(column) for column in zip(*values, strict=True))
            print(
                f"| {'/'.join(key)} | {sampled.mean():.1f} | {greedy.mean():.1f} | "
                f"{(greedy - sampled).mean():+.1f} | {int((greedy > sampled).sum())} of {len(values)} |"
            )


if __name__ == "__main__":
    main()
