"""Size of the env state a checkpoint keeps for an exact resume (``GraphVecEnv.get_state``), for every
env and budget: the env copies of the budget, reset and stepped 10 times with random actions.

Run: python benchmarks/env_state_size.py
"""

from __future__ import annotations

import numpy as np

from sb3_hgrn.common.vec_env import UnpicklableEnvError
from sb3_hgrn.experiments.config import BUDGETS, random_policy_config
from sb3_hgrn.experiments.runs import make_env


def state_size(env_name: str, budget: str) -> str:
    """``<copies> x <agents> agents: <MB>`` of one budget, or why its state cannot be pickled."""
    config = random_policy_config(env_name, budget)
    env = make_env(config, config.n_envs, seed=0)
    mask = env.reset().get("action_mask")
    n_actions = env.action_space.n if mask is None else mask.sum(axis=1)  # per slot
    rng = np.random.default_rng(0)
    for _ in range(10):
        env.step(rng.integers(0, n_actions, size=env.num_envs))
    try:
        size = f"{len(env.get_state()) / 1e6:.2f} MB"
    except UnpicklableEnvError as error:
        size = str(error)
    finally:
        env.close()
    return f"{config.n_envs} x {env.n_agents} agents: {size}"


def main() -> None:
    for env_name in ("surviving_v0", "uav_mbs_v0", "ctc_v0", "pursuit_v0"):
        for budget in BUDGETS:
            print(f"{env_name:13s} {budget:6s} {state_size(env_name, budget)}")


if __name__ == "__main__":
    main()
