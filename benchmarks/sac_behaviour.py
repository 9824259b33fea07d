"""Which half of SAC-HGRN fails: its actor as a policy, or its critic?

Run: python benchmarks/sac_behaviour.py --env uav_mbs_v0 --seed 1 [--act-with critic] [--param KEY=VALUE ...]
         [--budget cpu]
     python benchmarks/sac_behaviour.py --run RUN_FOLDER

Trains ``sac_hgrn`` at the ``--budget`` (default ``cpu``) of ``--env`` (the configuration of
``sb3-hgrn train``, ``--param`` over it) and evaluates the result. With ``--act-with critic`` the
agents act during training with the first critic's Boltzmann policy ``softmax(Q / alpha)`` instead
of the actor; the actor and the critic learn exactly as in SAC-HGRN (the critic's targets still
follow the actor's policy). ``--run`` evaluates a saved SACHGRN run instead of training one. Either
way it prints the team return of four policies on the evaluation envs: the actor (sampled and
greedy) and the critic (``softmax(Q / alpha)`` at the model's alpha, and greedy).
"""

from __future__ import annotations

import argparse
from typing import Any

import numpy as np
import torch as th

from sb3_hgrn.common.evaluation import evaluate_graph_policy
from sb3_hgrn.experiments.config import parse_assignments, resolve_config
from sb3_hgrn.experiments.runs import EVAL_SEED_OFFSET, load_run, make_env
from sb3_hgrn.presets import merge, preset_kwargs
from sb3_hgrn.sac_hgrn import SACHGRN
from sb3_hgrn.sac_hgrn.policies import SACHGRNPolicy


class CriticActingPolicy(SACHGRNPolicy):
    """A SAC-HGRN policy whose actions come from the first critic's ``softmax(Q / alpha)`` (greedy:
    its argmax); every network's memory advances as in :class:`SACHGRNPolicy`."""

    def act(self, obs: dict[str, th.Tensor], hidden: th.Tensor, deterministic: bool = False):
        _, new_hidden = super().act(obs, hidden, deterministic)
        observations, neighbors, groups = self.to_graphs(obs)
        critic_state = self.split_state(hidden.reshape(*observations.shape[:2], -1))[1]
        q_values, _ = self.critics[0](observations, self.graph_batch(neighbors, groups), critic_state)
        logits = q_values / self.temperature.per_agent(groups)
        if deterministic:
            actions = logits.argmax(dim=-1)
        else:
            actions = th.distributions.Categorical(logits=logits).sample()
        return actions.reshape(-1), new_hidden


def train(
    env_name: str, budget: str, seed: int, act_with: str, params: dict[str, Any]
) -> tuple[SACHGRN, Any]:
    """A ``sac_hgrn`` model trained at ``budget``, and its evaluation env."""
    config = resolve_config(env_name, "sac_hgrn", budget, seed, params=params)
    env = make_env(config, config.n_envs, config.seed)
    algorithm, kwargs = preset_kwargs("sac_hgrn", n_envs=env.num_envs)
    policy = CriticActingPolicy if act_with == "critic" else SACHGRNPolicy
    model = algorithm(policy, env, seed=seed, **merge(kwargs, config.hyperparams))
    model.learn(config.total_timesteps)
    return model, make_env(config, config.eval_n_envs, config.seed + EVAL_SEED_OFFSET)


def evaluate_halves(model: SACHGRN, env: Any, n_episodes: int) -> None:
    """Print the team return of the actor's and the critic's policies."""
    policy = model.policy
    for half, policy_class in (("actor", SACHGRNPolicy), ("critic", CriticActingPolicy)):
        policy.__class__ = policy_class  # the same networks, acting through the other half
        for mode, deterministic in (("sampled", False), ("greedy", True)):
            returns, _ = evaluate_graph_policy(
                model, env, n_episodes, deterministic, return_episode_rewards=True
            )
            print(f"{half:6s} {mode:7s}: team return {np.mean(returns):9.1f} +- {np.std(returns):7.1f}")


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--env", default="uav_mbs_v0")
    parser.add_argument("--budget", default="cpu")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--act-with", choices=("actor", "critic"), default="actor")
    parser.add_argument("--param", nargs="*", default=[])
    parser.add_argument("--run", help="evaluate this saved SACHGRN run instead of training")
    parser.add_argument("--episodes", type=int, default=12)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    th.set_num_threads(args.threads)
    if args.run:
        model, env, _ = load_run(args.run)
        if not isinstance(model, SACHGRN):
            raise SystemExit(f"{args.run} is not a SACHGRN run.")
    else:
        model, env = train(args.env, args.budget, args.seed, args.act_with, parse_assignments(args.param))
    print(f"alpha {model.policy.temperature.alpha.tolist()}")
    evaluate_halves(model, env, args.episodes)


if __name__ == "__main__":
    main()
