"""Train Soft-HGRN on a small Surviving map, compare it with a random policy and save the model.

Run: python examples/train_surviving.py [--timesteps N]
"""

import argparse
import time

import numpy as np

from sb3_hgrn import SoftHGRN, evaluate_graph_policy, make_graph_vec_env

parser = argparse.ArgumentParser()
parser.add_argument("--timesteps", type=int, default=400_000, help="agent-steps of training")
parser.add_argument("--agents", type=int, default=20)
parser.add_argument("--seed", type=int, default=0)
args = parser.parse_args()

env_kwargs = dict(n_agents=args.agents, map_size=16, max_cycles=100, n_resources=3)
env = make_graph_vec_env("surviving_v0", n_envs=4, seed=args.seed, env_kwargs=env_kwargs)
eval_env = make_graph_vec_env("surviving_v0", n_envs=4, seed=args.seed + 1000, env_kwargs=env_kwargs)


class RandomPolicy:
    def predict(self, obs, state=None, episode_start=None, deterministic=False):
        return np.random.randint(0, 5, size=len(obs["obs"])), state


random_return, random_std = evaluate_graph_policy(RandomPolicy(), eval_env, n_eval_episodes=8)
print(f"random policy: team return {random_return:.1f} +/- {random_std:.1f}")

model = SoftHGRN("GraphPolicy", env, seed=args.seed, verbose=0)
start = time.time()
model.learn(total_timesteps=args.timesteps, progress_bar=False)
print(f"trained {args.timesteps} agent-steps in {time.time() - start:.0f} s")
model.save("soft_hgrn_surviving.zip")

mean_return, std_return = evaluate_graph_policy(model, eval_env, n_eval_episodes=8)
print(f"Soft-HGRN:     team return {mean_return:.1f} +/- {std_return:.1f}  (saved soft_hgrn_surviving.zip)")
