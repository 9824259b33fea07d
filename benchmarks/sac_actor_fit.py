"""How closely a SAC-HGRN actor follows its critic, on the model's own episodes.

Run: python benchmarks/sac_actor_fit.py RUN_FOLDER [--steps 60] [--alpha 0.02]

Loads a saved SACHGRN run (a folder of ``sb3-hgrn train``), plays ``--steps`` env steps with its
policy on fresh copies of its env and prints, averaged over agent-steps: the actor's action entropy,
the entropy of the critic's Boltzmann policy ``softmax(Q / alpha)`` at ``--alpha``, how often the
actor's most likely action is the critic's best, and the mean gap between the critic's two best
Q-values.
"""

from __future__ import annotations

import argparse

import numpy as np
import torch as th

from sb3_hgrn.common.temperature import categorical_entropy
from sb3_hgrn.experiments.runs import load_run
from sb3_hgrn.sac_hgrn import SACHGRN


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("run")
    parser.add_argument("--steps", type=int, default=60)
    parser.add_argument("--alpha", type=float, default=0.02)
    args = parser.parse_args()
    th.set_num_threads(1)
    model, env, _ = load_run(args.run)
    if not isinstance(model, SACHGRN):
        raise SystemExit(f"{args.run} is not a SACHGRN run.")
    policy = model.policy
    figures: dict[str, list[float]] = {"actor": [], "critic": [], "agreement": [], "gap": []}
    obs, state, starts = env.reset(), None, np.ones(env.num_envs, dtype=bool)
    for _ in range(args.steps):
        observations, neighbors, groups = policy.to_graphs(policy.obs_to_tensor(obs)[0])
        hidden = np.zeros((env.num_envs, policy.state_dim), np.float32) if state is None else state[0][0]
        hidden = th.as_tensor(hidden * (1.0 - starts[:, None]), dtype=th.float32)
        actor_state, critic_state, *_ = policy.split_state(hidden.reshape(*observations.shape[:2], -1))
        graph = policy.graph_batch(neighbors, groups)
        with th.no_grad():
            logits, _ = policy.actor(observations, graph, actor_state)
            q_values, _ = policy.critics[0](observations, graph, critic_state)
        best_two = q_values.topk(2, dim=-1).values
        figures["actor"].append(categorical_entropy(logits).mean().item())
        figures["critic"].append(categorical_entropy(q_values / args.alpha).mean().item())
        figures["agreement"].append((logits.argmax(-1) == q_values.argmax(-1)).float().mean().item())
        figures["gap"].append((best_two[..., 0] - best_two[..., 1]).mean().item())
        actions, state = model.predict(obs, state=state, episode_start=starts)
        obs, _, starts, _ = env.step(actions)
    print(
        f"actor entropy {np.mean(figures['actor']):.3f} nats; critic's softmax(Q / {args.alpha:g}) entropy "
        f"{np.mean(figures['critic']):.3f} nats; actor's most likely action = critic's best in "
        f"{100 * np.mean(figures['agreement']):.0f} % of agent-steps; mean gap of the two best Q-values "
        f"{np.mean(figures['gap']):.3f}"
    )


if __name__ == "__main__":
    main()
