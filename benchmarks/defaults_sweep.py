"""Team return on a small Surviving map for several settings (how the defaults were chosen).

Run: python benchmarks/defaults_sweep.py [--timesteps 200000] [--seeds 0 1] [--settings ...]

Each line trains a preset with its defaults plus one override, then prints the mean team return over
8 evaluation episodes per seed (20 agents, 16 x 16 map, 3 resource points, 100-step episodes).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch as th

from sb3_hgrn import evaluate_graph_policy, make_graph_vec_env
from sb3_hgrn.presets import make_model

ENV_KWARGS = dict(n_agents=20, map_size=16, max_cycles=100, n_resources=3)
SETTINGS = {
    "defaults": ("soft_hgrn", {}),
    "target_entropy_ratio=0.1": ("soft_hgrn", dict(target_entropy_ratio=0.1)),
    "target_entropy_ratio=0.3": ("soft_hgrn", dict(target_entropy_ratio=0.3)),
    "alpha_optimizer=sgd": ("soft_hgrn", dict(alpha_optimizer="sgd", alpha_learning_rate=1e-3)),
    "alpha_log_space": ("soft_hgrn", dict(policy_kwargs=dict(alpha_log_space=True))),
    "hidden_dim=128": ("soft_hgrn", dict(policy_kwargs=dict(hidden_dim=128))),
    "stochastic=False": ("soft_hgrn", dict(stochastic=False)),
    "sac_hgrn tau=1.0": ("sac_hgrn", dict(tau=1.0)),
    "sac_hgrn tau=0.01": ("sac_hgrn", dict(tau=0.01)),
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
            preset, overrides = SETTINGS[name]
            model = make_model(preset, env, seed=seed, **overrides)
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
