"""Train Soft-HGRN for the predators of MPE2's simple_tag, chasing faster prey that move at random.

Needs MPE2 (installed with the extra dependencies: pip install -e ".[extra]"). The env-specific code is
predator_positions and make_env; docs/custom_envs.md walks through it.
Default (8 predators, 4 random prey, 2 obstacles, each agent observing its 4 nearest agents; 50 steps):
    python examples/tag_mpe2.py
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Sequence

import numpy as np
from mpe2 import simple_tag_v3

from sb3_hgrn import (
    DrivenAgents,
    GraphFromPositions,
    RandomGraphPolicy,
    SoftHGRN,
    evaluate_team_episodes,
    make_graph_vec_env,
)

CONTACT_REWARD = 10
"""What every predator earns per step for each (predator, prey) pair in contact."""


def predator_positions(env):
    """(n_predators, 2) positions of the predators (MPE2's adversaries, listed first) in possible_agents
    order."""
    world = env.unwrapped.world
    return np.array([agent.state.p_pos for agent in world.agents if agent.adversary])


def make_env(predators: int = 8, prey: int = 4, obstacles: int = 2, observed: int = 4, k: int = 3,
             max_cycles: int = 50, controller="random"):  # fmt: skip
    """The predators learn, ``controller`` drives the prey; an agent observes its ``observed`` nearest
    agents (of both sides) and a predator lists its ``k`` nearest fellow predators."""
    tag = simple_tag_v3.parallel_env(
        num_good=prey, num_adversaries=predators, num_obstacles=obstacles, max_cycles=max_cycles,
        num_agent_neighbors=observed,
    )  # fmt: skip
    hunters = DrivenAgents(tag, learners="adversary_", controller=controller)
    return GraphFromPositions(hunters, predator_positions, k=k)


def tag_report(episodes: list[dict], predators: int) -> str:
    """Team return and the (predator, prey) contacts per episode it counts."""
    returns = np.array([episode["r"] for episode in episodes])
    contacts = returns / (CONTACT_REWARD * predators)
    return (
        f"team return {returns.mean():.0f} +/- {returns.std():.0f} | contacts {contacts.mean():.1f} "
        f"per episode ({len(episodes)} episodes)"
    )


def main(argv: Sequence[str] | None = None) -> dict[str, list[dict]]:
    """Train with SoftHGRN's defaults, evaluate against the random policy and save; returns both
    evaluations' episodes."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--predators", type=int, default=8)
    parser.add_argument("--prey", type=int, default=4)
    parser.add_argument("--max-cycles", type=int, default=50, help="steps per episode")
    parser.add_argument("--copies", type=int, default=4, help="env copies stepped together")
    parser.add_argument("--timesteps", type=int, default=150_000, help="agent-steps of training")
    parser.add_argument("--learning-starts", type=int, default=10_000, help="agent-steps before training")
    parser.add_argument("--eval-episodes", type=int, default=20, help="team episodes per evaluation")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--save", default="soft_hgrn_tag.zip")
    args = parser.parse_args(argv)

    env_kwargs = dict(predators=args.predators, prey=args.prey, max_cycles=args.max_cycles)
    env = make_graph_vec_env(make_env, n_envs=args.copies, seed=args.seed, env_kwargs=env_kwargs)
    eval_env = make_graph_vec_env(make_env, n_envs=args.copies, seed=args.seed + 1000, env_kwargs=env_kwargs)
    print(f"{args.predators} predators against {args.prey} random prey per copy")

    random_policy = RandomGraphPolicy(eval_env, seed=args.seed)
    episodes = {"random": evaluate_team_episodes(random_policy, eval_env, n_eval_episodes=args.eval_episodes)}
    print(f"random predators: {tag_report(episodes['random'], args.predators)}")

    model = SoftHGRN("GraphPolicy", env, learning_starts=args.learning_starts, seed=args.seed, verbose=1)
    start = time.time()
    model.learn(total_timesteps=args.timesteps, log_interval=100)  # logs every 100 team episodes
    steps = model.num_timesteps
    print(f"trained {steps} agent-steps ({steps // env.num_envs} env steps) in {time.time() - start:.0f} s")
    model.save(args.save)

    episodes["soft_hgrn"] = evaluate_team_episodes(model, eval_env, n_eval_episodes=args.eval_episodes)
    print(f"Soft-HGRN:        {tag_report(episodes['soft_hgrn'], args.predators)}  (saved {args.save})")
    return episodes


if __name__ == "__main__":
    main()
