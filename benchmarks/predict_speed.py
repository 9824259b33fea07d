"""Cost of deploying a preset: milliseconds per ``predict`` call on a packaged env at its budget's sizes.

Run: python benchmarks/predict_speed.py [--envs surviving_v0 ctc_v0] [--presets soft_hgrn sac_hgrn]
     [--budget cpu] [--config FILE ...] [--calls 100] [--repeats 5] [--compile]

For each env and preset it builds an untrained model of the run's settings (as ``sb3-hgrn train --env
ENV --preset PRESET`` resolves them) on the budget's env copies, resets the env and times ``--calls``
calls of ``model.predict`` that carry the recurrent state from one call to the next, on the same
observations, ``--repeats`` times; the best time per call is printed. One torch thread.
``--compile`` also times the same calls with the networks built with ``compile_network=True`` (their
encoders and communication under ``torch.compile``) and prints the seconds its first call took (the
compilation).
"""

from __future__ import annotations

import argparse
import time

import torch as th

from sb3_hgrn.common.hgrn import HGRN
from sb3_hgrn.experiments.config import resolve_config
from sb3_hgrn.experiments.runs import make_env, new_model


def best_call_ms(model, obs, calls: int, repeats: int) -> float:
    """Best milliseconds per ``predict`` call over ``repeats`` rounds of ``calls`` chained calls."""
    state, best = None, float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        for _ in range(calls):
            _, state = model.predict(obs, state=state)
        best = min(best, (time.perf_counter() - start) / calls)
    return 1000 * best


def predict_row(env_name: str, preset: str, args: argparse.Namespace) -> str:
    """The table row of one env and preset: slots, eager ms and, with ``--compile``, compiled ms and
    the compilation's seconds."""
    config = resolve_config(env_name, preset, args.budget, config_file=args.config)
    env = make_env(config, config.n_envs, 0)
    model = new_model(config, env, verbose=0, tensorboard_log=None, device="cpu")
    obs = env.reset()
    eager_ms = best_call_ms(model, obs, args.calls, args.repeats)
    row = f"| {env_name} | {preset} | {env.num_envs} | {eager_ms:.2f} |"
    if args.compile:
        for module in model.policy.modules():  # as policy_kwargs=dict(compile_network=True) builds them
            if isinstance(module, HGRN):
                module.compile_options = {}
        start = time.perf_counter()
        model.predict(obs)
        compile_s = time.perf_counter() - start
        row += f" {best_call_ms(model, obs, args.calls, args.repeats):.2f} | {compile_s:.1f} |"
    return row


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
    parser.add_argument("--calls", type=int, default=100)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--compile", action="store_true", help="also time the network under torch.compile")
    args = parser.parse_args()
    th.set_num_threads(1)
    compiled = " compiled ms | compile s |" if args.compile else ""
    print(f"| env | preset | slots | ms per predict |{compiled}")
    print("|---|---|---|---|" + "---|---|" * args.compile)
    for env in args.envs:
        for preset in args.presets:
            print(predict_row(env, preset, args))


if __name__ == "__main__":
    main()
