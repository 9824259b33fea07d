"""Train Soft-HGRN for the red team of MAgent2's battle against a random blue team; report wins and kills.

Needs MAgent2 (installed with the extra dependencies: pip install -e ".[extra]"). The env-specific code
is red_cells, agents_left and make_env; docs/custom_envs.md walks through it.
Default (12 against 12 on a 20 x 20 map, 150-step episodes; about 2 minutes on one CPU thread):
    python examples/battle_magent2.py
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Sequence

import numpy as np
from magent2.environments import battle_v4

from sb3_hgrn import (
    AgentViewCNN,
    DrivenAgents,
    GraphFromPositions,
    RandomGraphPolicy,
    SoftHGRN,
    TeamFigures,
    evaluate_team_episodes,
    make_graph_vec_env,
)


def red_cells(env):
    """(n_red, 2) map cells of the red agents in possible_agents order (gone ones nan: not read)."""
    grid, red = env.unwrapped.env, env.unwrapped.handles[0]
    cells = np.full((len(env.possible_agents), 2), np.nan)
    cells[grid.get_agent_id(red)] = grid.get_pos(red)
    return cells


def agents_left(env):
    """The agents left on each side after a step (MAgent2 removes the dead at every step)."""
    grid = env.unwrapped.env
    return dict(zip(("red_left", "blue_left"), map(grid.get_num, env.unwrapped.handles), strict=True))


def make_env(map_size: int = 20, max_cycles: int = 150, controller="random"):
    """Red learns, ``controller`` drives blue; red agents list their 4 nearest team mates."""
    battle = battle_v4.parallel_env(map_size=map_size, max_cycles=max_cycles, minimap_mode=False)
    red = DrivenAgents(battle, learners="red_", controller=controller)
    return TeamFigures(GraphFromPositions(red, red_cells, k=4), agents_left)


def battle_report(episodes: list[dict], team_size: int) -> str:
    """Win / draw / loss rates (red's, by agents left at the end) and mean kills and losses."""
    red_left = np.array([episode["red_left"] for episode in episodes])
    blue_left = np.array([episode["blue_left"] for episode in episodes])
    returns = np.array([episode["r"] for episode in episodes])
    return (
        f"win {np.mean(red_left > blue_left):.0%} draw {np.mean(red_left == blue_left):.0%} "
        f"loss {np.mean(red_left < blue_left):.0%} | blue killed {np.mean(team_size - blue_left):.2f} "
        f"red lost {np.mean(team_size - red_left):.2f} of {team_size} | "
        f"team return {returns.mean():.1f} +/- {returns.std():.1f} ({len(episodes)} episodes)"
    )


def main(argv: Sequence[str] | None = None) -> dict[str, list[dict]]:
    """Train, evaluate against the random red policy and save; returns both evaluations' episodes."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--map-size", type=int, default=20, help="18: 6 against 6; 20: 12 against 12")
    parser.add_argument("--max-cycles", type=int, default=150, help="steps per episode")
    parser.add_argument("--features", choices=["flat", "cnn"], default="flat", help="how views are read")
    parser.add_argument("--copies", type=int, default=4, help="env copies stepped together")
    parser.add_argument("--timesteps", type=int, default=300_000, help="agent-steps of training")
    parser.add_argument("--learning-starts", type=int, default=10_000, help="agent-steps before training")
    parser.add_argument("--train-freq", type=int, default=1, help="vec-steps between gradient steps")
    parser.add_argument(
        "--buffer-size", type=int, default=60_000, help="replay agent-transitions (~7 kB each)"
    )
    parser.add_argument("--eval-episodes", type=int, default=16, help="team episodes per evaluation")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--save", default="soft_hgrn_battle.zip")
    args = parser.parse_args(argv)

    env_kwargs = dict(map_size=args.map_size, max_cycles=args.max_cycles)
    env = make_graph_vec_env(make_env, n_envs=args.copies, seed=args.seed, env_kwargs=env_kwargs)
    eval_env = make_graph_vec_env(make_env, n_envs=args.copies, seed=args.seed + 1000, env_kwargs=env_kwargs)
    team_size = env.n_agents  # battle gives both sides as many agents
    print(f"{team_size} red against {team_size} random blue agents per copy, map {args.map_size}")

    random_red = RandomGraphPolicy(eval_env, seed=args.seed)
    episodes = {"random": evaluate_team_episodes(random_red, eval_env, n_eval_episodes=args.eval_episodes)}
    print(f"random red: {battle_report(episodes['random'], team_size)}")

    # the (13, 13, 5) views: read by a small CNN, or flattened into the HGRN's encoder
    policy_kwargs = dict(features_extractor_class=AgentViewCNN) if args.features == "cnn" else None
    model = SoftHGRN(
        "GraphPolicy",
        env,
        learning_starts=args.learning_starts,
        train_freq=args.train_freq,
        buffer_size=args.buffer_size,
        policy_kwargs=policy_kwargs,
        seed=args.seed,
        verbose=1,
    )
    start = time.time()
    model.learn(total_timesteps=args.timesteps, log_interval=20)  # logs every 20 team episodes
    steps = model.num_timesteps
    print(f"trained {steps} agent-steps ({steps // env.num_envs} env steps) in {time.time() - start:.0f} s")
    model.save(args.save)

    episodes["soft_hgrn"] = evaluate_team_episodes(model, eval_env, n_eval_episodes=args.eval_episodes)
    print(f"Soft-HGRN:  {battle_report(episodes['soft_hgrn'], team_size)}  (saved {args.save})")
    return episodes


if __name__ == "__main__":
    main()
