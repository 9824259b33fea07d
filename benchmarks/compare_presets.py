"""Team return of every preset on Surviving at one equal budget and seed.

Run: python benchmarks/compare_presets.py [--agents 100] [--timesteps 2000000] [--threads 2]
     [--presets dqn dgn ...]

Each preset trains for ``--timesteps`` agent-steps on one env copy, then is evaluated for
``--eval-episodes`` team episodes (sampled actions for stochastic policies, greedy for the others).
Prints one Markdown table row per preset with the wall time.
"""

from __future__ import annotations

import argparse
import time

import torch as th

from sb3_hgrn import evaluate_graph_policy, make_graph_vec_env
from sb3_hgrn.presets import PRESETS, TABLE1, make_model


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--agents", type=int, default=100)
    parser.add_argument("--map-size", type=int, default=32)
    parser.add_argument("--max-cycles", type=int, default=500)
    parser.add_argument("--timesteps", type=int, default=2_000_000, help="agent-steps per preset")
    parser.add_argument("--eval-episodes", type=int, default=4)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--presets", nargs="+", default=list(TABLE1), choices=list(PRESETS))
    parser.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    args = parser.parse_args()
    th.set_num_threads(args.threads)
    env_kwargs = dict(n_agents=args.agents, map_size=args.map_size, max_cycles=args.max_cycles)
    print(
        f"Surviving {args.agents} agents, {args.timesteps} agent-steps per preset, seed {args.seed}, "
        f"{args.threads} torch thread(s)"
    )
    print("| preset | team return (mean +- std) | eval episodes | wall time |")
    print("|---|---|---|---|")
    for name in args.presets:
        env = make_graph_vec_env("surviving_v0", seed=args.seed, env_kwargs=env_kwargs)
        eval_env = make_graph_vec_env("surviving_v0", seed=args.seed + 1000, env_kwargs=env_kwargs)
        start = time.time()
        model = make_model(name, env, seed=args.seed)
        model.learn(args.timesteps)
        mean, std = evaluate_graph_policy(model, eval_env, n_eval_episodes=args.eval_episodes)
        print(
            f"| {name} | {mean:.0f} +- {std:.0f} | {args.eval_episodes} | {time.time() - start:.0f} s |",
            flush=True,
        )


if __name__ == "__main__":
    main()
