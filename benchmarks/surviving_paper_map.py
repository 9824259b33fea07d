"""Learning curve of a preset on the paper's Surviving map, as the original code is measured.

Run: python benchmarks/surviving_paper_map.py [--preset soft_hgrn] [--seeds 0 1 2] [--paper]
     [--param KEY=VALUE ...] [--env-param KEY=VALUE ...] [--save PREFIX] [--final-episodes N]
     [--device cpu|cuda|auto]

100 agents, 32 x 32 map, 8 resource points, 500-step episodes, one env copy. After every
``--eval-every`` env steps (default 5,000, up to ``--env-steps`` 15,000) it prints the team return over
4 episodes with 30 % epsilon-random actions (the original's test mode) and with the plain policy,
and the wall time of training so far. ``--paper`` uses the original's network size and schedule
(``make_model(..., paper=True)``). Two torch threads. ``--average-taus`` also evaluates, at each
checkpoint, Polyak averages of the online Q-network with those weights, kept beside the same
training run (``policy_kwargs.average_tau`` makes one of them the model's own deployed network).
``--final-episodes N`` then evaluates the final model over N further episodes with 30 % random
actions, after and apart from the protocol's 4, for a mean less noisy than theirs.
"""

from __future__ import annotations

import argparse
import time
from contextlib import contextmanager

import numpy as np
import torch as th
from stable_baselines3.common.callbacks import BaseCallback

from sb3_hgrn import evaluate_graph_policy, make_graph_vec_env
from sb3_hgrn.common.averaging import polyak_average
from sb3_hgrn.experiments.config import parse_assignments
from sb3_hgrn.experiments.policy_evaluation import EpsilonRandomPolicy
from sb3_hgrn.presets import make_model

PAPER_MAP = dict(n_agents=100, map_size=32, n_resources=8, max_cycles=500)


class Averages(BaseCallback):
    """Polyak averages of a policy's online acting network (Q-network or actor) by each weight
    ``tau``, updated after each gradient step (none without ``taus``)."""

    def __init__(self, policy, taus: list[float]):
        super().__init__()
        self.policy = policy
        self.networks = {tau: polyak_average(policy.online_network, tau) for tau in taus}
        self.updates_seen: int | None = None

    def _on_step(self) -> bool:
        if self.updates_seen is None:
            self.updates_seen = self.model._n_updates
        for _ in range(self.model._n_updates - self.updates_seen):
            for average in self.networks.values():
                average.update_parameters(self.policy.online_network)
        self.updates_seen = self.model._n_updates
        return True


def evaluate(model, eval_env, seed: int, episodes: int) -> tuple[float, float]:
    """Mean team return over ``episodes`` with 30 % epsilon-random actions, then with the plain policy."""
    noisy = EpsilonRandomPolicy(model, 0.3, seed=seed)
    eps_return = evaluate_graph_policy(noisy, eval_env, n_eval_episodes=episodes)[0]
    return eps_return, evaluate_graph_policy(model, eval_env, n_eval_episodes=episodes)[0]


@contextmanager
def deployed(model, network: th.nn.Module):
    """Let ``model`` act with ``network`` in place of its deployed network inside the block."""
    policy = model.policy
    name = f"{policy.acting_network_name}_average"
    own = policy.average_network
    setattr(policy, name, network)
    try:
        yield
    finally:
        setattr(policy, name, own)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--preset", default="soft_hgrn")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--env-steps", type=int, default=15_000)
    parser.add_argument("--eval-every", type=int, default=5_000, help="env steps between evaluations")
    parser.add_argument("--eval-episodes", type=int, default=4)
    parser.add_argument("--paper", action="store_true", help="the original's network size and schedule")
    parser.add_argument("--param", nargs="*", default=[], help="algorithm arguments, KEY=VALUE")
    parser.add_argument("--env-param", nargs="*", default=[], help="env arguments, KEY=VALUE")
    parser.add_argument("--final-episodes", type=int, default=0, help="further eps-0.3 episodes at the end")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--device", default="cpu", help="where the network runs: cpu, cuda or auto")
    parser.add_argument("--save", help="save each seed's final model as SAVE_seed<S>.zip")
    parser.add_argument(
        "--average-taus", type=float, nargs="*", default=[], help="also evaluate these averages"
    )
    args = parser.parse_args()
    if args.final_episodes < 0:
        parser.error(f"--final-episodes must be 0 or more, got {args.final_episodes}")
    th.set_num_threads(args.threads)
    env_kwargs = {**PAPER_MAP, **parse_assignments(args.env_param)}
    n_agents = env_kwargs["n_agents"]
    checkpoints = range(args.eval_every, args.env_steps + 1, args.eval_every)
    names = ["model"] + [f"average tau {tau}" for tau in args.average_taus]
    curves: dict[tuple[str, int], list[tuple[float, float]]] = {
        (name, step): [] for name in names for step in checkpoints
    }
    finals: list[float] = []
    for seed in args.seeds:
        env = make_graph_vec_env("surviving_v0", n_envs=1, seed=seed, env_kwargs=env_kwargs)
        eval_env = make_graph_vec_env("surviving_v0", n_envs=1, seed=seed + 1000, env_kwargs=env_kwargs)
        model = make_model(
            args.preset, env, paper=args.paper, seed=seed, device=args.device, **parse_assignments(args.param)
        )
        trained, train_time = 0, 0.0
        averages = Averages(model.policy, args.average_taus)
        for step in checkpoints:
            start = time.time()
            model.learn((step - trained) * n_agents, reset_num_timesteps=trained == 0, callback=averages)
            train_time += time.time() - start
            trained = step
            eps_return, plain = evaluate(model, eval_env, seed, args.eval_episodes)
            curves["model", step].append((eps_return, plain))
            print(
                f"seed {seed}  {step:6d} env steps ({model._n_updates} updates)  eps 0.3: {eps_return:8.1f}"
                f"  plain: {plain:8.1f}  training {train_time:6.0f} s",
                flush=True,
            )
            for tau, average in averages.networks.items():
                with deployed(model, average):
                    eps_return, plain = evaluate(model, eval_env, seed, args.eval_episodes)
                curves[f"average tau {tau}", step].append((eps_return, plain))
                print(f"    average tau {tau}: eps 0.3: {eps_return:8.1f}  plain: {plain:8.1f}", flush=True)
        if args.final_episodes:
            noisy = EpsilonRandomPolicy(model, 0.3, seed=seed + 2000)
            returns = evaluate_graph_policy(
                noisy, eval_env, args.final_episodes, return_episode_rewards=True
            )[0]
            finals.append(float(np.mean(returns)))
            print(
                f"seed {seed}  final model, {args.final_episodes} further episodes, eps 0.3: "
                f"{finals[-1]:8.1f} +- {np.std(returns) / np.sqrt(len(returns)):6.1f} (standard error)",
                flush=True,
            )
        if args.save:
            model.save(f"{args.save}_seed{seed}.zip")
    for (name, step), results in curves.items():
        eps_returns, plain_returns = np.array(results).T
        print(
            f"{name}, {step:6d} env steps: eps 0.3 {eps_returns.mean():8.1f} +- {eps_returns.std():6.1f}"
            f"  plain {plain_returns.mean():8.1f} +- {plain_returns.std():6.1f}  ({len(results)} seeds)"
        )
    if finals:
        print(
            f"final model, {args.final_episodes} further episodes: eps 0.3 {np.mean(finals):8.1f}"
            f" +- {np.std(finals):6.1f}  ({len(finals)} seeds)"
        )


if __name__ == "__main__":
    main()
