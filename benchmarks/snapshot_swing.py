"""How far frozen snapshots of the online network swing at the end of training, setting by setting.

Run: python benchmarks/snapshot_swing.py --env surviving_v0 --preset dqn --seeds 3
     [--settings "" learning_rate=2.5e-4 target_update_interval=20 gradient_steps=2] [--budget cpu]
     [--snapshots 8] [--window 0.2] [--episodes 4] [--threads 1]

Each setting is a comma-separated list of algorithm arguments over the budget's (as ``--param``;
``""`` is the budget's own). For each setting and seed the preset trains at the env's budget; over the
last ``--window`` of its agent-steps, ``--snapshots`` times at equal spacing, a copy of its online
network (the network that is trained and collects, not the deployed average) is evaluated for
``--episodes`` episodes on the same env seeds (``seed + 1000``) each time, with the plain policy
(greedy for the DQN-style presets), and its greedy actions are taken on a fixed probe batch of 32
replayed graphs. At the end the deployed network (the average, by default) is evaluated on the same
episodes. Per setting the table gives, as mean over seeds: the snapshots' mean team return, their
standard deviation within a run (the swing), the share of probe agents whose greedy action changed
from one snapshot to the next (the churn), the deployed network's return and the updates per run.
"""

from __future__ import annotations

import argparse
import copy
from typing import Any

import numpy as np
import torch as th
from stable_baselines3.common.callbacks import BaseCallback

from sb3_hgrn.common.evaluation import evaluate_graph_policy
from sb3_hgrn.experiments.config import parse_assignments, resolve_config
from sb3_hgrn.experiments.runs import EVAL_SEED_OFFSET, make_env, new_model

PROBE_GRAPHS = 32


class SnapshotProbe(BaseCallback):
    """Evaluates a copy of the online network at ``snapshot_steps`` (agent-steps, increasing) and
    records its greedy actions on a probe batch drawn from the replay buffer at the first one."""

    def __init__(self, snapshot_steps: list[int], eval_env: Any, seed: int, episodes: int):
        super().__init__()
        self.snapshot_steps = snapshot_steps
        self.eval_env, self.seed, self.episodes = eval_env, seed, episodes
        self.returns: list[float] = []
        self.probe_actions: list[th.Tensor] = []
        self._probe: Any = None

    def _on_step(self) -> bool:
        if self.snapshot_steps and self.num_timesteps >= self.snapshot_steps[0]:
            self.snapshot_steps.pop(0)
            self._snapshot()
        return True

    def _snapshot(self) -> None:
        policy = self.model.policy
        online = copy.deepcopy(policy)
        online.drop_average()
        online.set_training_mode(False)
        self.returns.append(evaluate(online, self.eval_env, self.seed, self.episodes))
        if self._probe is None:
            self._probe = self.model.replay_buffer.sample(PROBE_GRAPHS)
        batch = self._probe
        network = policy.online_network
        place = next(i for i, carried in enumerate(policy.recurrent_networks) if carried is network)
        with th.no_grad():
            outputs, _ = network(batch.observations, batch.neighbors, policy.split_state(batch.hidden)[place])
        self.probe_actions.append(outputs.argmax(dim=-1))


def evaluate(policy: Any, env: Any, seed: int, episodes: int) -> float:
    """Mean team return of ``policy`` (anything with a graph ``predict``) over ``episodes`` episodes of
    ``env`` reseeded with ``seed`` (the same episodes every call)."""
    env.seed(seed)
    returns, _ = evaluate_graph_policy(policy, env, n_eval_episodes=episodes, return_episode_rewards=True)
    return float(np.mean(returns))


def run(args: argparse.Namespace, setting: str, seed: int) -> dict[str, float]:
    """Train one run of ``setting`` and return its swing figures."""
    params = parse_assignments([item for item in setting.split(",") if item])
    config = resolve_config(args.env, args.preset, args.budget, seed=seed, params=params)
    env = make_env(config, config.n_envs, config.seed)
    eval_env = make_env(config, config.eval_n_envs, None)
    model = new_model(config, env, verbose=0, tensorboard_log=None, device="cpu")
    total = config.total_timesteps
    start = total * (1 - args.window)
    steps = [int(start + (total - start) * k / (args.snapshots - 1)) for k in range(args.snapshots)]
    probe = SnapshotProbe(steps, eval_env, seed + EVAL_SEED_OFFSET, args.episodes)
    model.learn(total, callback=probe)
    deployed = evaluate(model.policy, eval_env, seed + EVAL_SEED_OFFSET, args.episodes)
    churn = [
        (after != before).float().mean().item()
        for before, after in zip(probe.probe_actions, probe.probe_actions[1:], strict=False)
    ]
    env.close()
    eval_env.close()
    return {
        "mean": float(np.mean(probe.returns)),
        "swing": float(np.std(probe.returns)),
        "churn": float(np.mean(churn)),
        "deployed": deployed,
        "updates": float(model._n_updates),
    }


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--env", default="surviving_v0")
    parser.add_argument("--preset", default="dqn")
    parser.add_argument("--budget", default="cpu")
    parser.add_argument("--seeds", type=int, default=3, help="seeds 0..N-1")
    parser.add_argument("--settings", nargs="+", default=[""], metavar="KEY=VALUE,...")
    parser.add_argument("--snapshots", type=int, default=8)
    parser.add_argument("--window", type=float, default=0.2, help="fraction of training the snapshots span")
    parser.add_argument("--episodes", type=int, default=4)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    if args.snapshots < 2 or not 0 < args.window <= 1:
        parser.error("--snapshots needs at least 2 and --window a fraction in (0, 1].")
    th.set_num_threads(args.threads)
    print(
        f"{args.preset} on {args.env} ({args.budget}), seeds 0-{args.seeds - 1}, {args.snapshots} "
        f"snapshots over the last {args.window:.0%}, {args.episodes} episodes each"
    )
    print("| setting | snapshot mean | swing | churn | deployed | updates | per seed: mean / swing |")
    print("|---|---|---|---|---|---|---|")
    for setting in args.settings:
        results = [run(args, setting, seed) for seed in range(args.seeds)]
        mean = {key: np.mean([r[key] for r in results]) for key in results[0]}
        per_seed = ", ".join(f"{r['mean']:.1f} / {r['swing']:.1f}" for r in results)
        print(
            f"| {setting or 'budget'} | {mean['mean']:.1f} | {mean['swing']:.1f} | {mean['churn']:.3f} "
            f"| {mean['deployed']:.1f} | {mean['updates']:.0f} | {per_seed} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
