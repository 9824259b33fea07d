"""Cost of deploying a preset: milliseconds per ``predict`` call on a packaged env at its budget's sizes.

Run: python benchmarks/predict_speed.py [--envs surviving_v0 ctc_v0] [--presets soft_hgrn sac_hgrn]
     [--budget cpu] [--calls 100] [--repeats 5]

For each env and preset it builds an untrained model of the run's settings (as ``sb3-hgrn train --env
ENV --preset PRESET`` resolves them) on the budget's env copies, resets the env and times ``--calls``
calls of ``model.predict`` that carry the recurrent state from one call to the next, on the same
observations, ``--repeats`` times; the best time per call is printed. One torch thread.
"""

from __future__ import annotations

import argparse
import time

import torch as th

from sb3_hgrn.experiments.config import resolve_config
from sb3_hgrn.experiments.runs import make_env, new_model


def predict_ms(env_name: str, preset: str, budget: str, calls: int, repeats: int) -> tuple[int, float]:
    """The env's slot count and the best milliseconds per ``predict`` call over ``repeats`` rounds."""
    config = resolve_config(env_name, preset, budget)
    env = make_env(config, config.n_envs, 0)
    model = new_model(config, env, verbose=0, tensorboard_log=None, device="cpu")
    obs, state, best = env.reset(), None, float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        for _ in range(calls):
            _, state = model.predict(obs, state=state)
        best = min(best, (time.perf_counter() - start) / calls)
    return env.num_envs, 1000 * best


def main() -> None:
    formatter = argparse.RawDescriptionHelpFormatter
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=formatter)
    parser.add_argument("--envs", nargs="+", default=["surviving_v0", "ctc_v0"])
    parser.add_argument("--presets", nargs="+", default=["soft_hgrn", "sac_hgrn"])
    parser.add_argument("--budget", default="cpu")
    parser.add_argument("--calls", type=int, default=100)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    th.set_num_threads(1)
    print("| env | preset | slots | ms per predict |")
    print("|---|---|---|---|")
    for env in args.envs:
        for preset in args.presets:
            slots, ms = predict_ms(env, preset, args.budget, args.calls, args.repeats)
            print(f"| {env} | {preset} | {slots} | {ms:.2f} |")


if __name__ == "__main__":
    main()
