"""How closely a SAC-HGRN actor follows its critic, on the model's own episodes.

Run: python benchmarks/sac_actor_fit.py RUN_FOLDER [--steps 60] [--alpha 0.02] [--fit-steps 0]

Loads a saved SACHGRN run (a folder of ``sb3-hgrn train``), plays ``--steps`` env steps with its
policy on fresh copies of its env and prints, averaged over agent-steps: the actor's action entropy,
the entropy of the critic's Boltzmann policy ``softmax(Q / alpha)`` at ``--alpha``, how often the
actor's most likely action is the critic's best, and the mean gap between the critic's two best
Q-values. With ``--fit-steps N`` it then trains the actor alone for N Adam steps (learning rate
1e-3) on ``KL(softmax(Q / alpha) || pi)`` of the frozen critic over the first 80 % of those steps,
and prints the actor's figures on the last 20 % after 50, 200 and N steps: whether the actor can
follow a critic that stands still.
"""

from __future__ import annotations

import argparse

import numpy as np
import torch as th

from sb3_hgrn.common.soft_math import boltzmann_divergence
from sb3_hgrn.common.temperature import categorical_entropy
from sb3_hgrn.experiments.runs import load_run
from sb3_hgrn.sac_hgrn import SACHGRN


def collect(model: SACHGRN, env, steps: int) -> list[tuple]:
    """``steps`` graph batches ``(observations, graph, groups, actor state, critic state)`` of the model's
    own episodes (recurrent states as its policy carried them)."""
    policy, batches = model.policy, []
    obs, state, starts = env.reset(), None, np.ones(env.num_envs, dtype=bool)
    for _ in range(steps):
        observations, neighbors, groups = policy.to_graphs(policy.obs_to_tensor(obs)[0])
        hidden = np.zeros((env.num_envs, policy.state_dim), np.float32) if state is None else state[0][0]
        hidden = th.as_tensor(hidden * (1.0 - starts[:, None]), dtype=th.float32)
        actor_state, critic_state, *_ = policy.split_state(hidden.reshape(*observations.shape[:2], -1))
        graph = policy.graph_batch(neighbors, groups)
        batches.append((observations, graph, groups, actor_state, critic_state))
        actions, state = model.predict(obs, state=state, episode_start=starts)
        obs, _, starts, _ = env.step(actions)
    return batches


def fit_figures(model: SACHGRN, batches: list[tuple], alpha: float) -> dict[str, float]:
    """Mean actor entropy, critic Boltzmann entropy, argmax agreement and top-2 Q gap over ``batches``."""
    policy = model.policy
    figures: dict[str, list[float]] = {"actor": [], "critic": [], "agreement": [], "gap": []}
    for observations, graph, groups, actor_state, critic_state in batches:
        with th.no_grad():
            logits, _ = policy.actor_logits(observations, graph, actor_state, groups)
            q_values, _ = policy.critics[0](observations, graph, critic_state)
        best_two = q_values.topk(2, dim=-1).values
        figures["actor"].append(categorical_entropy(logits).mean().item())
        figures["critic"].append(categorical_entropy(q_values / alpha).mean().item())
        figures["agreement"].append((logits.argmax(-1) == q_values.argmax(-1)).float().mean().item())
        figures["gap"].append((best_two[..., 0] - best_two[..., 1]).mean().item())
    return {name: float(np.mean(values)) for name, values in figures.items()}


def describe(figures: dict[str, float], alpha: float) -> str:
    return (
        f"actor entropy {figures['actor']:.3f} nats; critic's softmax(Q / {alpha:g}) entropy "
        f"{figures['critic']:.3f} nats; actor's most likely action = critic's best in "
        f"{100 * figures['agreement']:.0f} % of agent-steps; mean gap of the two best Q-values "
        f"{figures['gap']:.3f}"
    )


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("run")
    parser.add_argument("--steps", type=int, default=60)
    parser.add_argument("--alpha", type=float, default=0.02)
    parser.add_argument("--fit-steps", type=int, default=0)
    args = parser.parse_args()
    th.set_num_threads(1)
    model, env, _ = load_run(args.run)
    if not isinstance(model, SACHGRN):
        raise SystemExit(f"{args.run} is not a SACHGRN run.")
    batches = collect(model, env, args.steps)
    print(describe(fit_figures(model, batches, args.alpha), args.alpha))
    if args.fit_steps <= 0:
        return
    split = int(0.8 * len(batches))
    train, held_out = batches[:split], batches[split:]
    policy, critic = model.policy, model.policy.critics[0]
    optimizer = th.optim.Adam(policy.actor.parameters(), lr=1e-3)
    rng = np.random.default_rng(0)
    for step in range(1, args.fit_steps + 1):
        observations, graph, groups, actor_state, critic_state = train[rng.integers(len(train))]
        with th.no_grad():
            q_values, _ = critic(observations, graph, critic_state)
        logits, _ = policy.actor_logits(observations, graph, actor_state, groups)
        loss = boltzmann_divergence(th.log_softmax(logits, dim=-1), q_values, th.tensor(args.alpha)).mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        if step in (50, 200, args.fit_steps):
            figures = describe(fit_figures(model, held_out, args.alpha), args.alpha)
            print(f"after {step} actor steps on the frozen critic, held-out steps: {figures}")


if __name__ == "__main__":
    main()
