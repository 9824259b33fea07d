"""Train Soft-HGRN for the predators of MAgent2's adversarial_pursuit, tagging faster prey that move randomly.

Needs MAgent2 (installed with the extra dependencies: pip install -e ".[extra]"). The env-specific code
is predator_cells and make_env. A predator earns 1 for each prey it tags and pays 0.2 for every tag
action, so tagging at random costs the team about 176 per episode, and standing still earns 0: the
team must learn when a tag is worth its price, and trap the prey, who move 1.5 cells per step against
the predators' 1.
Default (11 predators against 22 random prey on a 30 x 30 map, 150-step episodes):
    python examples/adversarial_pursuit_magent2.py
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Sequence

import numpy as np
from magent2.environments import adversarial_pursuit_v4

from sb3_hgrn import (
    DrivenAgents,
    GraphFromPositions,
    RandomGraphPolicy,
    SoftHGRN,
    evaluate_team_episodes,
    make_graph_vec_env,
)


def predator_cells(env):
    """(n_predators, 2) map cells of the predators in the wrapper's possible_agents order (gone ones
    -1000: not read; predators never die here)."""
    grid, predators = env.unwrapped.env, env.unwrapped.handles[0]
    cells = np.full((len(env.possible_agents), 2), -1000.0)
    cells[env.learner_rows_of(grid.get_agent_id(predators))] = grid.get_pos(predators)
    return cells


def make_env(map_size: int = 30, max_cycles: int = 150, tag_penalty: float = -0.2, k: int = 4,
             controller="random"):  # fmt: skip
    """The predators learn, ``controller`` drives the prey; a predator lists its ``k`` nearest fellows.
    The map's size sets the teams: 11 predators and 22 prey on 30 x 30, 5 and 10 on 20 x 20."""
    pursuit = adversarial_pursuit_v4.parallel_env(
        map_size=map_size, max_cycles=max_cycles, tag_penalty=tag_penalty, minimap_mode=False
    )
    predators = DrivenAgents(pursuit, learners="predator_", controller=controller)
    return GraphFromPositions(predators, predator_cells, k=k)


def pursuit_report(episodes: list[dict]) -> str:
    """The team return per episode: tags of prey, less 0.2 for every tag action."""
    returns = np.array([episode["r"] for episode in episodes])
    return f"team return {returns.mean():.1f} +/- {returns.std():.1f} ({len(episodes)} episodes)"


def main(argv: Sequence[str] | None = None) -> dict[str, list[dict]]:
    """Train with SoftHGRN's defaults, evaluate against the random policy and save; returns both
    evaluations' episodes."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--map-size", type=int, default=30, help="30: 11 predators; 20: 5")
    parser.add_argument("--max-cycles", type=int, default=150, help="steps per episode")
    parser.add_argument("--copies", type=int, default=4, help="env copies stepped together")
    parser.add_argument("--timesteps", type=int, default=200_000, help="agent-steps of training")
    parser.add_argument("--learning-starts", type=int, default=10_000, help="agent-steps before training")
    parser.add_argument("--eval-episodes", type=int, default=16, help="team episodes per evaluation")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--save", default="soft_hgrn_pursuit.zip")
    args = parser.parse_args(argv)

    env_kwargs = dict(map_size=args.map_size, max_cycles=args.max_cycles)
    env = make_graph_vec_env(make_env, n_envs=args.copies, seed=args.seed, env_kwargs=env_kwargs)
    eval_env = make_graph_vec_env(make_env, n_envs=args.copies, seed=args.seed + 1000, env_kwargs=env_kwargs)
    print(f"{env.n_agents} predators against random prey per copy, map {args.map_size}")

    random_policy = RandomGraphPolicy(eval_env, seed=args.seed)
    episodes = {"random": evaluate_team_episodes(random_policy, eval_env, n_eval_episodes=args.eval_episodes)}
    print(f"random predators: {pursuit_report(episodes['random'])}")

    model = SoftHGRN("GraphPolicy", env, learning_starts=args.learning_starts, seed=args.seed, verbose=1)
    start = time.time()
    model.learn(total_timesteps=args.timesteps, log_interval=20)  # logs every 20 team episodes
    steps = model.num_timesteps
    print(f"trained {steps} agent-steps ({steps // env.num_envs} env steps) in {time.time() - start:.0f} s")
    model.save(args.save)

    episodes["soft_hgrn"] = evaluate_team_episodes(model, eval_env, n_eval_episodes=args.eval_episodes)
    print(f"Soft-HGRN: {pursuit_report(episodes['soft_hgrn'])}  (saved {args.save})")
    return episodes


if __name__ == "__main__":
    main()
