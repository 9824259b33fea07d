"""How a single-agent run learns: its training return and temperature figures every few thousand steps.

Run: python benchmarks/single_agent_trace.py --env Acrobot-v1 --preset discrete_sac --steps 40000
     [--seed 0] [--every 5000] [--param gradient_steps=-1 actor_loss=standard] [--eval-episodes 5]

Trains the preset with the settings of ``sb3_hgrn/hyperparams/<preset>.yml`` for the env (``--param``
overrides them as the CLI's does: dotted keys reach into ``policy_kwargs``), one torch thread, and
prints every ``--every`` env steps the mean return of the last 10 training episodes and the last
logged ``train/`` figures (the actor's entropy, the Boltzmann entropy that alpha steers, alpha, the
losses). At the end it prints the greedy and the sampled return over ``--eval-episodes`` episodes
and the wall time.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch as th
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.evaluation import evaluate_policy

from sb3_hgrn.experiments.config import parse_assignments
from sb3_hgrn.experiments.single_agent import SINGLE_AGENT_PRESETS, env_settings, make_model

SHOWN = ("actor_entropy", "entropy", "alpha", "critic_loss", "actor_loss", "loss")
"""The ``train/`` figures printed, where the algorithm logs them."""


class Trace(BaseCallback):
    """Prints the training return and the logged ``train/`` figures every ``every`` env steps."""

    def __init__(self, every: int):
        super().__init__()
        self.every = every

    def _on_step(self) -> bool:
        if self.num_timesteps % self.every == 0:
            returns = [episode["r"] for episode in self.model.ep_info_buffer][-10:]
            logged = self.model.logger.name_to_value
            figures = "  ".join(
                f"{key} {logged[f'train/{key}']:.3f}" for key in SHOWN if f"train/{key}" in logged
            )
            mean = f"{np.mean(returns):8.1f}" if returns else "       -"
            print(f"{self.num_timesteps:8d} steps  training return {mean}  {figures}", flush=True)
        return True


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--env", default="Acrobot-v1")
    parser.add_argument("--preset", choices=SINGLE_AGENT_PRESETS, default="discrete_sac")
    parser.add_argument("--steps", type=int, default=40_000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--every", type=int, default=5_000)
    parser.add_argument("--eval-episodes", type=int, default=5)
    parser.add_argument("--param", nargs="*", default=[], metavar="KEY=VALUE")
    args = parser.parse_args()
    th.set_num_threads(1)
    settings = env_settings(args.preset, args.env, parse_assignments(args.param))
    start = time.perf_counter()
    model = make_model(args.preset, args.env, settings, args.seed)
    model.learn(args.steps, callback=Trace(args.every))
    wall = time.perf_counter() - start
    env = model.get_env()
    greedy, _ = evaluate_policy(model, env, n_eval_episodes=args.eval_episodes, deterministic=True)
    sampled, _ = evaluate_policy(model, env, n_eval_episodes=args.eval_episodes)
    episodes = args.eval_episodes
    print(f"greedy return {greedy:.1f}, sampled return {sampled:.1f} ({episodes} episodes); {wall:.0f} s")


if __name__ == "__main__":
    main()
