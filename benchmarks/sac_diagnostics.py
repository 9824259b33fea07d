"""Why an actor-critic run scores what it does: its actor's lag, entropy band and critic error.

Run: python benchmarks/sac_diagnostics.py FOLDER [FOLDER ...] [--fraction 0.1]

Reads the TensorBoard logs of every finished SAC-HGRN-style run folder under the given folders (those
of ``sb3-hgrn train``, ``sweep`` or ``reproduce`` with a ``config.yml``, an ``eval.json`` and logs of
``train/actor_entropy``) and prints one row per run, each figure the mean over the last ``--fraction``
of its logged training rounds:

- the actor's entropy and the entropy alpha steers (``train/entropy``: that of the critic's Boltzmann
  policy ``softmax(Q / alpha)``, the policy the actor learns toward, or with ``alpha_entropy="actor"``
  the actor's own), in nats, and their difference, the actor's lag (positive: the actor is more random
  than that policy; 0 by construction with ``alpha_entropy="actor"``);
- the target entropy alpha steers toward, and alpha;
- the critic loss (its squared TD error, per entry);
- the last logged mean training team return and the saved model's evaluation.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from sb3_hgrn.experiments.figures import read_scalars
from sb3_hgrn.experiments.run_folder import read_eval

TAGS = ("train/actor_entropy", "train/entropy", "train/target_entropy", "train/alpha", "train/critic_loss")
TRAINING_RETURN = "rollout/ep_team_rew_mean"


def run_row(folder: Path, fraction: float) -> str | None:
    """The Markdown row of one run folder (``None`` for a run that logs no actor)."""
    scalars = read_scalars(folder, (), optional=(*TAGS, TRAINING_RETURN))
    if any(tag not in scalars for tag in TAGS):
        return None
    tail = {}
    for tag in TAGS:
        values = scalars[tag][1]
        tail[tag] = float(np.mean(values[-max(1, int(round(fraction * len(values)))) :]))
    lag = tail["train/actor_entropy"] - tail["train/entropy"]
    training = scalars[TRAINING_RETURN][1][-1] if TRAINING_RETURN in scalars else float("nan")
    evaluation = read_eval(folder)
    saved = float("nan") if evaluation is None else evaluation["mean"]
    return (
        f"| {folder} | {tail['train/actor_entropy']:.3f} | {tail['train/entropy']:.3f} | {lag:+.3f} "
        f"| {tail['train/target_entropy']:.3f} | {tail['train/alpha']:.3g} | {tail['train/critic_loss']:.4f} "
        f"| {training:.1f} | {saved:.1f} |"
    )


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("folders", nargs="+", type=Path)
    parser.add_argument("--fraction", type=float, default=0.1, help="last fraction of the training rounds")
    args = parser.parse_args()
    if not 0 < args.fraction <= 1:
        parser.error("--fraction must lie in (0, 1].")
    print(
        "| run | actor entropy | steered entropy | actor lag | target | alpha | critic loss "
        "| training return | saved model |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for root in args.folders:
        for config in sorted(root.rglob("config.yml")):
            folder = config.parent
            row = run_row(folder, args.fraction) if (folder / "tensorboard").is_dir() else None
            if row is not None:
                print(row, flush=True)


if __name__ == "__main__":
    main()
