"""Training wall time of SoftDQN and DiscreteSAC against SB3's DQN on one schedule, with and without
fused Adam.

Run: python benchmarks/single_agent_speed.py [--env CartPole-v1] [--steps 12000] [--repeats 3]
     python benchmarks/single_agent_speed.py --profile 2000

Each setting trains from scratch for ``--steps`` env steps with the RL Zoo DQN's CartPole schedule
(one round of 128 gradient steps of batch 64 per 256 env steps, ``[64, 64]`` networks) on one torch
thread. The settings take turns, ``--repeats`` times, so that a machine's drift touches them alike;
the best time of each is printed as seconds per 100k env steps with its ratio to DQN's. "unfused"
is SB3's Adam (one loop over the parameters, ``foreach=False``), "fused" the single-agent classes'
default (``fused=True``). With ``--profile N`` it instead prints cProfile's cumulative times of N
gradient steps of DiscreteSAC (fused) after ``--steps`` env steps of training.
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import time

import torch as th
from stable_baselines3 import DQN

from sb3_hgrn import DiscreteSAC, SoftDQN

SCHEDULE = dict(
    gamma=0.99,
    learning_rate=2.3e-3,
    batch_size=64,
    buffer_size=100_000,
    learning_starts=1000,
    train_freq=256,
    gradient_steps=128,
    target_update_interval=128,
)
ADAM = {"unfused": {"foreach": False}, "fused": {"fused": True}}
SETTINGS = [(DQN, "unfused")] + [(algorithm, adam) for algorithm in (SoftDQN, DiscreteSAC) for adam in ADAM]


def new_model(algorithm: type, adam: str, env_id: str) -> DQN | SoftDQN | DiscreteSAC:
    """A fresh model (seed 0) with the schedule, ``[64, 64]`` networks and the named Adam."""
    policy_kwargs = {"net_arch": [64, 64], "optimizer_kwargs": ADAM[adam]}
    return algorithm("MlpPolicy", env_id, seed=0, policy_kwargs=policy_kwargs, **SCHEDULE)


def train_seconds(algorithm: type, adam: str, env_id: str, steps: int) -> float:
    """Wall seconds of ``learn(steps)`` of a fresh model."""
    model = new_model(algorithm, adam, env_id)
    start = time.perf_counter()
    model.learn(steps)
    return time.perf_counter() - start


def profile_gradient_steps(env_id: str, steps: int, gradient_steps: int) -> None:
    """Print the profile of ``gradient_steps`` steps of DiscreteSAC after ``steps`` env steps."""
    model = new_model(DiscreteSAC, "fused", env_id).learn(steps)
    profiler = cProfile.Profile()
    profiler.runcall(model.train, gradient_steps, SCHEDULE["batch_size"])
    pstats.Stats(profiler).sort_stats("cumulative").print_stats(30)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="CartPole-v1")
    parser.add_argument("--steps", type=int, default=12_000)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--profile", type=int, metavar="N", help="profile N gradient steps of DiscreteSAC")
    args = parser.parse_args()
    th.set_num_threads(1)
    if args.profile:
        profile_gradient_steps(args.env, args.steps, args.profile)
        return
    times: dict[tuple[str, str], list[float]] = {}
    for _ in range(args.repeats):
        for algorithm, adam in SETTINGS:
            seconds = train_seconds(algorithm, adam, args.env, args.steps)
            times.setdefault((algorithm.__name__, adam), []).append(seconds)
    per_100k = {key: min(values) * 100_000 / args.steps for key, values in times.items()}
    dqn = per_100k[("DQN", "unfused")]
    print(f"{args.env}, {args.steps} env steps, best of {args.repeats}:")
    print("| algorithm | Adam | wall s / 100k env steps | x DQN |\n|---|---|---|---|")
    for (name, adam), seconds in per_100k.items():
        print(f"| {name} | {adam} | {seconds:.0f} | {seconds / dqn:.2f} |")


if __name__ == "__main__":
    main()
