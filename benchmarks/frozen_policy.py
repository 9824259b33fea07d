"""A trained Surviving model run frozen against the same model trained on, on the paper's map.

Run: python benchmarks/frozen_policy.py MODEL.zip [--episodes 2] [--reset-every 0 1 20] [--seed 0]

``MODEL.zip`` is a SoftHGRN or SACHGRN model of ``benchmarks/surviving_paper_map.py --save``.
For each ``--reset-every`` value (0: never) one episode runs with the frozen model, its recurrent
state reset every that many steps, and prints the team return, the team reward per 50 steps and
the share of each action, and the share of agent-steps without food in the agent's 3 x 3 view with
the action shares there. Then ``--episodes`` frozen episodes (seeds ``--seed`` on) run twice: as
the model acts, and with a uniformly random move wherever an agent sees no food. Last the model
collects ``--episodes`` episodes with its weights frozen
(``gradient_steps=0``) and ``--episodes`` more while it is trained on as in ``learn`` (from an empty
buffer, after 32 env steps of random actions), and prints their team returns; with ``--move-drift``,
every 25 gradient steps of that training the action shares the online Q-network samples for agents
without food in view (on states probed from a frozen episode).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch as th
from numpy.lib.stride_tricks import sliding_window_view
from stable_baselines3.common.callbacks import BaseCallback

from sb3_hgrn import make_graph_vec_env
from sb3_hgrn.experiments.runs import algorithm_of_zip

PAPER_MAP = dict(n_agents=100, map_size=32, n_resources=8, max_cycles=500)
N_MOVES = 4  # actions 0-3 move, 4 eats


def surviving_env(vec_env):
    """The :class:`~sb3_hgrn.envs.surviving_v0.SurvivingEnv` inside a one-copy graph VecEnv."""
    env = vec_env.envs[0]
    while not hasattr(env, "food_grid"):
        env = env.env
    return env


def food_in_view(env) -> np.ndarray:
    """Food ``(n_agents,)`` in each agent's 3 x 3 window (walls count 0)."""
    window_sums = sliding_window_view(env.food_grid().clip(min=0), (3, 3)).sum(axis=(2, 3))
    x, y = env.agent_cells().T
    return window_sums[x - 1, y - 1]


def frozen_episode(model, seed: int, reset_every: int, random_moves_without_food: bool = False) -> str:
    """One episode of the frozen model on a fresh env: its return, reward per 50 steps, action
    shares, and the share of agent-steps without food in view with the action shares there.
    ``random_moves_without_food`` replaces the model's action by a uniformly random move wherever
    an agent sees no food."""
    env = make_graph_vec_env("surviving_v0", n_envs=1, seed=seed, env_kwargs=PAPER_MAP)
    surviving, rng = surviving_env(env), np.random.default_rng(seed)
    obs, state, starts = env.reset(), None, np.ones(env.num_envs, dtype=bool)
    rewards, counts, counts_without_food = [], np.zeros(env.action_space.n), np.zeros(env.action_space.n)
    for step in range(PAPER_MAP["max_cycles"]):
        if reset_every and step % reset_every == 0:
            starts = np.ones(env.num_envs, dtype=bool)
        actions, state = model.predict(obs, state=state, episode_start=starts)
        no_food = food_in_view(surviving) == 0
        if random_moves_without_food:
            actions = np.where(no_food, rng.integers(0, N_MOVES, size=actions.size), actions)
        counts += np.bincount(actions, minlength=counts.size)
        counts_without_food += np.bincount(actions[no_food], minlength=counts.size)
        obs, reward, starts, _ = env.step(actions)
        rewards.append(reward.sum())
    per_50 = np.add.reduceat(rewards, np.arange(0, len(rewards), 50)).round().astype(int).tolist()
    shares = (counts / counts.sum()).round(3).tolist()
    shares_without_food = (counts_without_food / counts_without_food.sum()).round(3).tolist()
    return (
        f"team return {sum(rewards):.0f}; per 50 steps {per_50}; action shares {shares}; "
        f"no food in view at {counts_without_food.sum() / counts.sum():.2f} of agent-steps, "
        f"action shares there {shares_without_food}"
    )


def probe_states(
    model, seed: int, steps: int = 300, every: int = 30
) -> list[tuple[dict, np.ndarray, np.ndarray]]:
    """Observations, recurrent states and no-food masks of a frozen episode, every ``every`` steps."""
    env = make_graph_vec_env("surviving_v0", n_envs=1, seed=seed, env_kwargs=PAPER_MAP)
    surviving = surviving_env(env)
    obs, starts = env.reset(), np.ones(env.num_envs, dtype=bool)
    state = (np.zeros((1, env.num_envs, model.policy.state_dim), dtype=np.float32),)
    probes = []
    for step in range(1, steps + 1):
        no_food = food_in_view(surviving) == 0
        actions, next_state = model.predict(obs, state=state, episode_start=starts)
        if step % every == 0:
            probes.append((obs, (state[0][0] * (1.0 - starts[:, None])).astype(np.float32), no_food))
        state = next_state
        obs, _, starts, _ = env.step(actions)
    return probes


class MoveDrift(BaseCallback):
    """Every ``every`` gradient steps, print the action shares the online network samples for the
    probed agents that see no food."""

    def __init__(self, probes: list[tuple[dict, np.ndarray, np.ndarray]], every: int = 25):
        super().__init__()
        self.probes, self.every, self.printed = probes, every, None

    def _on_step(self) -> bool:
        updates = self.model._n_updates
        if updates % self.every == 0 and updates != self.printed:
            self.printed = updates
            policy, counts = self.model.policy, np.zeros(self.model.action_space.n)
            with th.no_grad():
                for obs, hidden, no_food in self.probes:
                    obs_tensor, _ = policy.obs_to_tensor(obs)
                    actions, _ = policy.act_with(policy.q_net, obs_tensor, th.as_tensor(hidden))
                    counts += np.bincount(actions.numpy()[no_food], minlength=counts.size)
            shares = (counts / counts.sum()).round(2).tolist()
            print(f"  update {updates}: action shares without food in view {shares}")
        return True


def collected_returns(model, seed: int, episodes: int, train: bool, callback=None) -> list[int]:
    """Team returns of ``episodes`` episodes collected by ``learn``, with or without updates."""
    env = make_graph_vec_env("surviving_v0", n_envs=1, seed=seed, env_kwargs=PAPER_MAP)
    model.set_env(env)
    model.learning_starts = 32 * env.num_envs if train else 0
    model.gradient_steps = 1 if train else 0
    model._team_episodes.clear()
    model.learn(episodes * PAPER_MAP["max_cycles"] * env.num_envs, callback=callback)
    return [round(episode["r"]) for episode in model._team_episodes]


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("model")
    parser.add_argument("--episodes", type=int, default=2)
    parser.add_argument("--reset-every", type=int, nargs="+", default=[0, 1, 20])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument(
        "--move-drift", action="store_true", help="while trained on, print the moves of agents without food"
    )
    args = parser.parse_args()
    th.set_num_threads(args.threads)
    model = algorithm_of_zip(Path(args.model)).load(args.model)
    if args.move_drift and not hasattr(model.policy, "act_with"):
        raise SystemExit("--move-drift needs a SoftHGRN model (it samples the online Q-network)")
    for reset_every in args.reset_every:
        figures = frozen_episode(model, args.seed, reset_every)
        print(f"frozen, memory reset every {reset_every or 'never'}: {figures}")
    for seed in range(args.seed, args.seed + args.episodes):
        print(f"frozen, seed {seed}: {frozen_episode(model, seed, 0)}")
        randomised = frozen_episode(model, seed, 0, random_moves_without_food=True)
        print(f"frozen, random moves without food in view, seed {seed}: {randomised}")
    print(f"collected frozen: {collected_returns(model, args.seed, args.episodes, train=False)}")
    drift = MoveDrift(probe_states(model, args.seed)) if args.move_drift else None
    trained_on = collected_returns(model, args.seed, args.episodes, train=True, callback=drift)
    print(f"collected while trained on: {trained_on}")


if __name__ == "__main__":
    main()
