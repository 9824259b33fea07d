"""Greedy team return on the single-skill tasks of the learning tests, per setting and seed.

Run: python benchmarks/learning_tasks.py [--seeds 0 1 2] [--tasks ...] [--settings ...]

Each task needs one piece of the learner (``tests/toy_envs.py`` describes them): ``invest``
delayed rewards and stopping at terminations (optimum 8.8; no bootstrapping 4.0; bootstrapping
through the termination 6.0; ``invest_gamma_0.95`` the same with the default discount),
``invest_time_limit`` bootstrapping at time limits (right: 6.0; treating them as terminations:
8.8), ``tag`` a costly but necessary action (optimum 4 in expectation, never tagging 0), ``memory``
a cue recalled two steps later (4.0 with memory, 2 by guessing), ``memory_4`` and ``memory_8`` four
and eight steps later. The models and budgets
are those of ``tests/test_learning.py``; one torch thread.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch as th

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the tests' toy envs

from tests.toy_envs import CueMemoryEnv, InvestEnv, costly_tag_env, greedy_return, train_on  # noqa: E402

TASKS = {
    # name: (env factory, agent-steps, SACHGRN agent-steps, algorithm overrides, evaluation episodes)
    "invest": (lambda: InvestEnv(4), 6_000, 6_000, dict(gamma=0.8), 16),
    "invest_time_limit": (lambda: InvestEnv(4, time_limit=True), 6_000, 6_000, dict(gamma=0.8), 16),
    "invest_gamma_0.95": (lambda: InvestEnv(4), 6_000, 6_000, dict(gamma=0.95), 16),
    "tag": (costly_tag_env, 8_000, 8_000, {}, 32),
    "memory": (lambda: CueMemoryEnv(4, delay=1), 6_000, 12_000, {}, 16),
    "memory_4": (lambda: CueMemoryEnv(4, delay=3), 12_000, 12_000, {}, 16),
    "memory_8": (lambda: CueMemoryEnv(4, delay=7), 24_000, 24_000, {}, 16),
}
SETTINGS = {
    "SoftHGRN": ("SoftHGRN", {}),
    "SACHGRN": ("SACHGRN", {}),
    "SACHGRN actor_loss=standard": ("SACHGRN", dict(actor_loss="standard")),
    "SACHGRN actor_loss=standard eps=0.3": (
        "SACHGRN",
        dict(actor_loss="standard", exploration_initial_eps=0.3, exploration_final_eps=0.3),
    ),
    "SACHGRN 6,000 agent-steps": ("SACHGRN", dict(timesteps=6_000)),
    "SoftHGRN recurrent=False": ("SoftHGRN", dict(policy_kwargs=dict(recurrent=False))),
    "SACHGRN recurrent=False": ("SACHGRN", dict(policy_kwargs=dict(recurrent=False))),
    "SoftHGRN sequence_length=8": ("SoftHGRN", dict(sequence_length=8)),
    "SACHGRN sequence_length=8": ("SACHGRN", dict(sequence_length=8)),
    "SoftHGRN sequence_length=16": ("SoftHGRN", dict(sequence_length=16)),
    "SACHGRN sequence_length=16": ("SACHGRN", dict(sequence_length=16)),
    "SACHGRN recurrent=False sequence_length=8": (
        "SACHGRN",
        dict(sequence_length=8, policy_kwargs=dict(recurrent=False)),
    ),
}


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--tasks", nargs="+", default=list(TASKS), choices=list(TASKS))
    parser.add_argument("--settings", nargs="+", default=list(SETTINGS), choices=list(SETTINGS))
    args = parser.parse_args()
    th.set_num_threads(1)
    for task in args.tasks:
        make_env, timesteps, sac_timesteps, task_kwargs, episodes = TASKS[task]
        for name in args.settings:
            algorithm, overrides = SETTINGS[name]
            overrides = dict(overrides)
            steps = overrides.pop("timesteps", sac_timesteps if algorithm == "SACHGRN" else timesteps)
            start, returns = time.time(), []
            for seed in args.seeds:
                model = train_on(algorithm, make_env, steps, seed=seed, **task_kwargs, **overrides)
                returns.append(greedy_return(model, make_env, n_episodes=episodes, seed=100 + seed))
            print(
                f"{task:18s} {name:36s} {steps:6d} steps  return {np.mean(returns):6.2f} "
                f"(seeds: {', '.join(f'{r:.2f}' for r in returns)})  {time.time() - start:4.0f} s",
                flush=True,
            )


if __name__ == "__main__":
    main()
