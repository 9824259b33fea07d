"""Env steps/s of the four environments at the paper's sizes, with uniformly random valid actions.

Run: python benchmarks/env_speed.py [--steps 2000]

For each env prints one Markdown row: steps/s through the array API with the communication graph
(``step_arrays`` + ``neighbors`` per step, episodes restarting as they end) and through a one-copy
graph VecEnv, beside the original code's figure on a 2-core CPU where one is known.
"""

from __future__ import annotations

import argparse

from throughput import best_rate  # benchmarks/throughput.py, beside this script

from sb3_hgrn import RandomGraphPolicy, make_graph_vec_env
from sb3_hgrn.common.vec_env import as_graph_env

# name -> (registered env, env_kwargs, the original's env steps/s)
SETTINGS = {
    "Surviving, 100 agents": ("surviving_v0", {}, "~2,200"),
    "UAV-MBS, 20 UAVs, raster obs": ("uav_mbs_v0", {}, "~105"),
    "UAV-MBS, 20 UAVs, compact obs": ("uav_mbs_v0", {"observation_mode": "compact"}, "-"),
    "Pursuit, 25 predators, evader prey": ("pursuit_v0", {}, "-"),
    "Pursuit, 25 predators, random prey": ("pursuit_v0", {"prey_controller": "random"}, "-"),
    "CTC, 20 hunters + 10 + 10 banks": ("ctc_v0", {}, "~370"),
}


def rates(name: str, env_kwargs: dict, steps: int) -> tuple[float, float]:
    vec_env = make_graph_vec_env(name, seed=0, env_kwargs=env_kwargs)
    env = as_graph_env(vec_env.envs[0])
    policy = RandomGraphPolicy(vec_env, seed=0)
    observation = vec_env.reset()
    actions = [policy.predict(observation)[0] for _ in range(steps)]

    def array_api():
        env.reset_arrays(seed=0)
        for step_actions in actions:
            _, _, terminated, truncated, _ = env.step_arrays(step_actions)
            env.neighbors()
            if (terminated | truncated).all():
                env.reset_arrays()

    def graph_vec_env():
        for step_actions in actions:
            vec_env.step(step_actions)

    return best_rate(array_api, steps), best_rate(graph_vec_env, steps)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--steps", type=int, default=2000)
    args = parser.parse_args()
    print("| env | array API + graph (steps/s) | graph VecEnv (steps/s) | original (steps/s) |")
    print("|---|---|---|---|")
    for label, (name, env_kwargs, original) in SETTINGS.items():
        array_rate, vec_rate = rates(name, env_kwargs, args.steps)
        print(f"| {label} | {array_rate:,.0f} | {vec_rate:,.0f} | {original} |", flush=True)


if __name__ == "__main__":
    main()
