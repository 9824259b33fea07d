"""Team return of Soft-HGRN on a small Surviving map for several settings (how the defaults were chosen).

Run: python benchmarks/defaults_sweep.py [--timesteps 200000] [--seeds 0 1]

Each line trains with SoftHGRN's defaults plus one override, then prints the mean team return over
8 evaluation episodes per seed (20 agents, 16 x 16 map, 3 resource points, 100-step episodes).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch as th

from sb3_hgrn import SoftHGRN, evaluate_graph_policy, make_graph_vec_env

ENV_KWARGS = dict(n_agents=20, map_size=16, max_cycles=100, n_resources=3)
SETTINGS = {
    "defaults": {},
    "target_entropy_ratio=0.1": dict(target_entropy_ratio=0.1),
    "target_entropy_ratio=0.3": dict(target_entropy_ratio=0.3),
    "alpha_optimizer=sgd": dict(alpha_optimizer="sgd", alpha_learning_rate=1e-3),
    "alpha_log_space": dict(policy_kwargs=dict(alpha_log_space=True)),
    "hidden_dim=128": dict(policy_kwargs=dict(hidden_dim=128)),
    "stochastic=False": dict(stochastic=False),
}


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--timesteps", type=int, default=200_000)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--settings", nargs="+", default=list(SETTINGS), choices=list(SETTINGS))
    args = parser.parse_args()
    th.set_num_threads(2)
    for name in args.settings:
        returns, start = [], time.time()
        for seed in args.seeds:
            env = make_graph_vec_env("surviving_v0", n_envs=4, seed=seed, env_kwargs=ENV_KWARGS)
            eval_env = make_graph_vec_env("surviving_v0", n_envs=4, seed=seed + 1000, env_kwargs=ENV_KWARGS)
            model = SoftHGRN("GraphPolicy", env, seed=seed, **SETTINGS[name])
            model.learn(args.timesteps)
            returns.append(evaluate_graph_policy(model, eval_env, n_eval_episodes=8)[0])
        print(
            f"{name:28s} team return {np.mean(returns):8.1f} "
            f"(seeds: {', '.join(f'{r:.0f}' for r in returns)})"
            f"  {time.time() - start:5.0f} s",
            flush=True,
        )


if __name__ == "__main__":
    main()
