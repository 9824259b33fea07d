"""Train Soft-HGRN on PettingZoo's Knights Archers Zombies: archers and knights hold off zombies together.

Needs PettingZoo's butterfly envs (pygame; installed with the extra dependencies: pip install -e ".[extra]").
The env-specific code is player_positions, players_left, within_space and make_env; docs/custom_envs.md
walks through it.
Default (4 archers and 4 knights, vector observations, episodes of at most 300 steps):
    python examples/kaz_pettingzoo.py
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Sequence

import numpy as np
import supersuit
from pettingzoo.butterfly import knights_archers_zombies_v11

from sb3_hgrn import (
    GraphFromPositions,
    RandomGraphPolicy,
    SoftHGRN,
    TeamFigures,
    evaluate_team_episodes,
    make_graph_vec_env,
)


def player_positions(env):
    """(n_players, 2) screen positions in pixels, archers then knights as in possible_agents (dead ones
    far off the screen)."""
    kaz = env.unwrapped
    rows = kaz.get_vector_state()[: len(kaz.possible_agents), -4:-2]  # x / width, y / height; dead: 0
    return np.where(rows.any(axis=1, keepdims=True), rows * kaz.screen_dims, -1000.0)


def players_left(env):
    """The archers and knights still alive after a step (a zombie that touches one kills it)."""
    return {"players_left": len(env.unwrapped.player_list)}


def within_space(obs, space):
    """``obs`` clipped to ``space``: a relative position can pass the declared [-1, 1] by a pixel."""
    return np.clip(obs, space.low, space.high)


def make_env(archers: int = 4, knights: int = 4, max_zombies: int = 10, max_cycles: int = 300, k: int = 3):
    """The players see everything as vectors (one row per player, weapon and zombie) and list their
    ``k`` nearest fellow players."""
    kaz = knights_archers_zombies_v11.parallel_env(
        num_archers=archers, num_knights=knights, max_zombies=max_zombies, max_cycles=max_cycles
    )
    kaz = supersuit.observation_lambda_v0(kaz, within_space)
    return TeamFigures(GraphFromPositions(kaz, player_positions, k=k), players_left)


def kaz_report(episodes: list[dict], players: int) -> str:
    """Zombies killed (the team return: 1 per kill), players left and episode lengths."""
    returns = np.array([episode["r"] for episode in episodes])
    left = np.mean([episode["players_left"] for episode in episodes])
    length = np.mean([episode["l"] for episode in episodes])
    return (
        f"zombies killed {returns.mean():.1f} +/- {returns.std():.1f} | players left {left:.2f} of {players} "
        f"| {length:.0f} steps ({len(episodes)} episodes)"
    )


def main(argv: Sequence[str] | None = None) -> dict[str, list[dict]]:
    """Train with SoftHGRN's defaults, evaluate against the random policy and save; returns both
    evaluations' episodes."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--archers", type=int, default=4)
    parser.add_argument("--knights", type=int, default=4)
    parser.add_argument("--max-cycles", type=int, default=300, help="steps per episode at most")
    parser.add_argument("--copies", type=int, default=4, help="env copies stepped together")
    parser.add_argument("--timesteps", type=int, default=150_000, help="agent-steps of training")
    parser.add_argument("--learning-starts", type=int, default=10_000, help="agent-steps before training")
    parser.add_argument("--eval-episodes", type=int, default=20, help="team episodes per evaluation")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--save", default="soft_hgrn_kaz.zip")
    args = parser.parse_args(argv)

    env_kwargs = dict(archers=args.archers, knights=args.knights, max_cycles=args.max_cycles)
    env = make_graph_vec_env(make_env, n_envs=args.copies, seed=args.seed, env_kwargs=env_kwargs)
    eval_env = make_graph_vec_env(make_env, n_envs=args.copies, seed=args.seed + 1000, env_kwargs=env_kwargs)
    print(f"{args.archers} archers and {args.knights} knights per copy")

    random_policy = RandomGraphPolicy(eval_env, seed=args.seed)
    episodes = {"random": evaluate_team_episodes(random_policy, eval_env, n_eval_episodes=args.eval_episodes)}
    print(f"random policy: {kaz_report(episodes['random'], env.n_agents)}")

    model = SoftHGRN("GraphPolicy", env, learning_starts=args.learning_starts, seed=args.seed, verbose=1)
    start = time.time()
    model.learn(total_timesteps=args.timesteps, log_interval=20)  # logs every 20 team episodes
    steps = model.num_timesteps
    print(f"trained {steps} agent-steps ({steps // env.num_envs} env steps) in {time.time() - start:.0f} s")
    model.save(args.save)

    episodes["soft_hgrn"] = evaluate_team_episodes(model, eval_env, n_eval_episodes=args.eval_episodes)
    print(f"Soft-HGRN:     {kaz_report(episodes['soft_hgrn'], env.n_agents)}  (saved {args.save})")
    return episodes


if __name__ == "__main__":
    main()
