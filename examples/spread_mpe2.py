"""Train Soft-HGRN on MPE2's simple_spread, agents that see only their nearest mates and landmarks.

Needs MPE2 (installed with the extra dependencies: pip install -e ".[extra]"). The env-specific code is
agent_positions, landmarks_covered and make_env; docs/custom_envs.md walks through it.
Default (6 agents, 6 landmarks, each agent observing 3 of each; about 4 minutes on one CPU thread):
    python examples/spread_mpe2.py
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Sequence

import numpy as np
from mpe2 import simple_spread_v3

from sb3_hgrn import (
    GraphFromPositions,
    RandomGraphPolicy,
    SoftHGRN,
    TeamFigures,
    evaluate_team_episodes,
    make_graph_vec_env,
)


def agent_positions(env):
    """(n_agents, 2) positions of the agents in possible_agents order."""
    return np.array([agent.state.p_pos for agent in env.unwrapped.world.agents])


def landmarks_covered(env):
    """The landmarks with an agent within 0.1 (MPE2's "occupied"), and their mean distance to the nearest."""
    landmarks = np.array([landmark.state.p_pos for landmark in env.unwrapped.world.landmarks])
    nearest = np.linalg.norm(landmarks[:, None] - agent_positions(env)[None], axis=-1).min(axis=1)
    return {"covered": int((nearest < 0.1).sum()), "distance": float(nearest.mean())}


def make_env(n_agents: int = 6, observed: int = 3, k: int = 3, max_cycles: int = 25):
    """Each agent observes its ``observed`` nearest mates and landmarks and lists its ``k`` nearest mates."""
    spread = simple_spread_v3.parallel_env(
        N=n_agents, max_cycles=max_cycles, num_agent_neighbors=observed, num_landmark_neighbors=observed
    )
    return TeamFigures(GraphFromPositions(spread, agent_positions, k=k), landmarks_covered)


def spread_report(episodes: list[dict]) -> str:
    """Team return and the landmarks covered at the episodes' ends."""
    returns = np.array([episode["r"] for episode in episodes])
    covered = np.mean([episode["covered"] for episode in episodes])
    distance = np.mean([episode["distance"] for episode in episodes])
    return (
        f"team return {returns.mean():.1f} +/- {returns.std():.1f} | at the end {covered:.2f} landmarks "
        f"covered, {distance:.3f} from a landmark to its nearest agent ({len(episodes)} episodes)"
    )


def main(argv: Sequence[str] | None = None) -> dict[str, list[dict]]:
    """Train, evaluate against the random policy and save; returns both evaluations' episodes."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--agents", type=int, default=6, help="agents, and as many landmarks")
    parser.add_argument("--observed", type=int, default=3, help="nearest mates and landmarks observed")
    parser.add_argument("--k", type=int, default=3, help="nearest mates in an agent's neighbour list")
    parser.add_argument("--max-cycles", type=int, default=25, help="steps per episode")
    parser.add_argument("--copies", type=int, default=4, help="env copies stepped together")
    parser.add_argument("--timesteps", type=int, default=300_000, help="agent-steps of training")
    parser.add_argument("--learning-starts", type=int, default=10_000, help="agent-steps before training")
    parser.add_argument("--train-freq", type=int, default=1, help="vec-steps between gradient steps")
    parser.add_argument("--eval-episodes", type=int, default=32, help="team episodes per evaluation")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--save", default="soft_hgrn_spread.zip")
    args = parser.parse_args(argv)

    env_kwargs = dict(n_agents=args.agents, observed=args.observed, k=args.k, max_cycles=args.max_cycles)
    env = make_graph_vec_env(make_env, n_envs=args.copies, seed=args.seed, env_kwargs=env_kwargs)
    eval_env = make_graph_vec_env(make_env, n_envs=args.copies, seed=args.seed + 1000, env_kwargs=env_kwargs)
    print(f"{env.n_agents} agents per copy, each observing {args.observed} mates and landmarks")

    random_policy = RandomGraphPolicy(eval_env, seed=args.seed)
    episodes = {"random": evaluate_team_episodes(random_policy, eval_env, n_eval_episodes=args.eval_episodes)}
    print(f"random policy: {spread_report(episodes['random'])}")

    model = SoftHGRN(
        "GraphPolicy",
        env,
        learning_starts=args.learning_starts,
        train_freq=args.train_freq,
        seed=args.seed,
        verbose=1,
    )
    start = time.time()
    model.learn(total_timesteps=args.timesteps, log_interval=100)  # logs every 100 team episodes
    steps = model.num_timesteps
    print(f"trained {steps} agent-steps ({steps // env.num_envs} env steps) in {time.time() - start:.0f} s")
    model.save(args.save)

    episodes["soft_hgrn"] = evaluate_team_episodes(model, eval_env, n_eval_episodes=args.eval_episodes)
    print(f"Soft-HGRN:     {spread_report(episodes['soft_hgrn'])}  (saved {args.save})")
    return episodes


if __name__ == "__main__":
    main()
