"""Why an actor-critic run scores what it does: its actor's lag, entropy band and critic error.

Run: python benchmarks/sac_diagnostics.py FOLDER [FOLDER ...] [--fraction 0.1]

Reads the TensorBoard logs of every finished run folder under the given folders (those of ``sb3-hgrn
train``, ``sweep`` or ``reproduce`` with a ``config.yml`` and an ``eval.json``) and prints one row per
run, each figure the mean over the last ``--fraction`` of its logged training rounds:

- the actor's entropy and the entropy alpha steers (``train/entropy``: that of the critic's Boltzmann
  policy ``softmax(Q / alpha)``, the policy the actor learns toward, or with ``alpha_entropy="actor"``
  the actor's own), in nats, and their difference, the actor's lag (positive: the actor is more random
  than that policy; 0 by construction with ``alpha_entropy="actor"``);
- the target entropy alpha steers toward, and alpha;
- the squared TD error per entry of one critic (SAC-HGRN-style runs log ``train/critic_loss``, the
  sum over their ``n_critics`` critics, read from the run's settings);
- the last logged mean training team return and the saved model's evaluation.

Runs whose actor is never trained (SACHGRN's ``actor_steps="auto"`` with the defaults) and runs
without an actor (SoftHGRN-style: ``train/q_loss``, the Q-network's squared TD error per entry) get
a row too, with no actor entropy or lag, so the two algorithms' entropy bands and critic errors on
the same env sit side by side.
"""

from __future__ import annotations

import argparse
import inspect
from pathlib import Path

import numpy as np
import yaml

from sb3_hgrn.experiments.figures import read_scalars
from sb3_hgrn.experiments.run_folder import read_eval
from sb3_hgrn.sac_hgrn.policies import SACHGRNPolicy

STEERING = ("train/entropy", "train/target_entropy", "train/alpha")
ACTOR_CRITIC = ("train/actor_entropy", "train/critic_loss")
"""Logged by SACHGRN-style runs; the actor's entropy only where the actor trains."""
Q_LEARNING = ("train/q_loss",)
TRAINING_RETURN = "rollout/ep_team_rew_mean"
DEFAULT_N_CRITICS = inspect.signature(SACHGRNPolicy.__init__).parameters["n_critics"].default


def n_critics(folder: Path) -> int:
    """The critics of a run: its ``policy_kwargs.n_critics`` (``config.yml``), else the default."""
    config = yaml.safe_load((folder / "config.yml").read_text()) or {}
    kwargs = (config.get("extra") or {}).get("algorithm_kwargs") or {}
    return int((kwargs.get("policy_kwargs") or {}).get("n_critics", DEFAULT_N_CRITICS))


def run_row(folder: Path, fraction: float) -> str | None:
    """The Markdown row of one run folder (``None`` for a run that logs neither critic error)."""
    scalars = read_scalars(folder, (), optional=(*STEERING, *ACTOR_CRITIC, *Q_LEARNING, TRAINING_RETURN))
    critics = "train/critic_loss" in scalars
    if any(tag not in scalars for tag in STEERING) or not (critics or "train/q_loss" in scalars):
        return None
    tail = {}
    for tag in (*STEERING, *ACTOR_CRITIC, *Q_LEARNING):
        if tag in scalars:
            values = scalars[tag][1]
            tail[tag] = float(np.mean(values[-max(1, int(round(fraction * len(values)))) :]))
    entropies = f"- | {tail['train/entropy']:.3f} | -"  # no actor trained (or none at all)
    if "train/actor_entropy" in tail:
        entropies = f"{tail['train/actor_entropy']:.3f} | {tail['train/entropy']:.3f} | "
        entropies += f"{tail['train/actor_entropy'] - tail['train/entropy']:+.3f}"
    td_error = tail["train/critic_loss"] / n_critics(folder) if critics else tail["train/q_loss"]
    training = scalars[TRAINING_RETURN][1][-1] if TRAINING_RETURN in scalars else float("nan")
    evaluation = read_eval(folder)
    saved = float("nan") if evaluation is None else evaluation["mean"]
    return (
        f"| {folder} | {entropies} | {tail['train/target_entropy']:.3f} | {tail['train/alpha']:.3g} "
        f"| {td_error:.4f} | {training:.1f} | {saved:.1f} |"
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
        "| run | actor entropy | steered entropy | actor lag | target | alpha | TD error per critic "
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
