"""Cost of one gradient step of a preset on a packaged env at its budget's sizes, under option variants.

Run: python benchmarks/update_speed.py [--envs surviving_v0 ctc_v0] [--presets soft_hgrn sac_hgrn]
     [--budget cpu] [--config FILE ...] [--steps 20] [--repeats 3] [--average-calls 500]
     [--variant unfused policy_kwargs.optimizer_kwargs.foreach=False] [--variant NAME KEY=VALUE ...]

For each env and preset it builds one model per variant (the library's settings of that run, as
``sb3-hgrn train --env ENV --preset PRESET [--config FILE]`` resolves them, with the variant's
``--param``-style assignments over them; the variant ``default`` adds none), fills its replay buffer
with 300 steps of collection on one env copy, then times ``--steps`` gradient steps (``model.train``).
The variants take turns, ``--repeats`` times, so that a machine's drift touches them alike, and the best
time of each is printed in milliseconds per gradient step with its ratio to the first variant's. One
torch thread. ``--average-calls N`` also prints, per variant, the best time of one update of the
deployed Polyak average (``policy.update_average()``, a part of every gradient step) over rounds of
``N`` calls.
"""

from __future__ import annotations

import argparse
import time

import torch as th

from sb3_hgrn.experiments.config import parse_assignments, resolve_config
from sb3_hgrn.experiments.runs import make_env, new_model

FILL_STEPS = 300


def build(env: str, preset: str, budget: str, params: dict, config_file: list[str] | None = None):
    """A model of the run's settings with ``params`` over them, its buffer filled by collection."""
    config = resolve_config(env, preset, budget, params=params, config_file=config_file)
    model = new_model(config, make_env(config, 1, 0), verbose=0, tensorboard_log=None, device="cpu")
    model.learning_starts = 10**12  # collection only while filling
    model.learn(FILL_STEPS * model.n_envs)
    return model


def average_update_ms(model, calls: int, repeats: int) -> float:
    """Best milliseconds of one ``policy.update_average()`` over ``repeats`` rounds of ``calls``."""
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        for _ in range(calls):
            model.policy.update_average()
        best = min(best, (time.perf_counter() - start) / calls)
    return 1000 * best


def main() -> None:
    formatter = argparse.RawDescriptionHelpFormatter
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=formatter)
    parser.add_argument("--envs", nargs="+", default=["surviving_v0", "ctc_v0"])
    parser.add_argument("--presets", nargs="+", default=["soft_hgrn", "sac_hgrn"])
    parser.add_argument("--budget", default="cpu")
    parser.add_argument(
        "--config", nargs="+", default=None, metavar="FILE",
        help="config files of a user env (MODULE:ATTR in --envs), as sb3-hgrn train --config takes them",
    )  # fmt: skip
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--average-calls", type=int, default=0, help="also time the Polyak average's update")
    parser.add_argument(
        "--variant", nargs="+", action="append", metavar=("NAME", "KEY=VALUE"),
        help="a name and its --param assignments (default: unfused against default)",
    )  # fmt: skip
    args = parser.parse_args()
    variants = args.variant or [["unfused", "policy_kwargs.optimizer_kwargs.foreach=False"], ["default"]]
    th.set_num_threads(1)
    print(f"| env | preset | {' | '.join(f'{v[0]} ms' for v in variants)} | x {variants[0][0]} |")
    print(f"|---|---|{'---|' * len(variants)}---|")
    for env in args.envs:
        for preset in args.presets:
            models = [
                build(env, preset, args.budget, parse_assignments(v[1:]), args.config) for v in variants
            ]
            best = [float("inf")] * len(models)
            for _ in range(args.repeats):
                for index, model in enumerate(models):
                    start = time.perf_counter()
                    model.train(args.steps, model.batch_size)
                    best[index] = min(best[index], (time.perf_counter() - start) / args.steps)
            ratios = " / ".join(f"{b / best[0]:.2f}" for b in best[1:])
            print(f"| {env} | {preset} | {' | '.join(f'{1000 * b:.1f}' for b in best)} | {ratios} |")
            if args.average_calls:
                averages = [average_update_ms(model, args.average_calls, args.repeats) for model in models]
                print(f"|   Polyak average update | | {' | '.join(f'{ms:.3f}' for ms in averages)} | |")


if __name__ == "__main__":
    main()
