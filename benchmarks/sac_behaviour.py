"""Which half of a trained SAC-HGRN fails: its actor as a policy, or its critic?

Run: python benchmarks/sac_behaviour.py RUN_FOLDER [--episodes 12]

Loads a saved SACHGRN run (a folder of ``sb3-hgrn train``) onto its evaluation envs and prints the
team return of four policies of the same networks: the actor (sampled and greedy) and the first
critic (its Boltzmann policy ``softmax(Q / alpha)`` at the model's alpha, and greedy).
"""

from __future__ import annotations

import argparse

import numpy as np
import torch as th

from sb3_hgrn.common.evaluation import evaluate_graph_policy
from sb3_hgrn.experiments.runs import load_run
from sb3_hgrn.sac_hgrn import SACHGRN
from sb3_hgrn.sac_hgrn.policies import SACHGRNPolicy


class CriticActingPolicy(SACHGRNPolicy):
    """A SAC-HGRN policy that acts with its first critic's Boltzmann policy (``critic_act``)."""

    act = SACHGRNPolicy.critic_act


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("run")
    parser.add_argument("--episodes", type=int, default=12)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    th.set_num_threads(args.threads)
    model, env, _ = load_run(args.run)
    if not isinstance(model, SACHGRN):
        raise SystemExit(f"{args.run} is not a SACHGRN run.")
    print(f"alpha {model.policy.temperature.alpha.tolist()}")
    for half, policy_class in (("actor", SACHGRNPolicy), ("critic", CriticActingPolicy)):
        model.policy.__class__ = policy_class  # the same networks, acting through the other half
        for mode, deterministic in (("sampled", False), ("greedy", True)):
            returns, _ = evaluate_graph_policy(
                model, env, args.episodes, deterministic, return_episode_rewards=True
            )
            print(f"{half:6s} {mode:7s}: team return {np.mean(returns):9.1f} +- {np.std(returns):7.1f}")


if __name__ == "__main__":
    main()
