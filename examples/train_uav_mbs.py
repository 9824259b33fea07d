"""Train Soft-HGRN UAVs on UAV-MBS, compare them with a random policy and save the model.

Small default (10 UAVs, 60 users, compact 44-dim observations; a minute or two on 2 CPU cores):
    python examples/train_uav_mbs.py
The paper's setting (20 UAVs, 120 users, 1,613-dim raster observations; the replay buffer then takes
about 13 kB per agent-transition, so keep --buffer-size small on a CPU machine):
    python examples/train_uav_mbs.py --uavs 20 --users 120 --observation raster --copies 1 \
        --buffer-size 100000 --timesteps 2000000
"""

import argparse
import time

import numpy as np

from sb3_hgrn import RandomGraphPolicy, SoftHGRN, evaluate_graph_policy, make_graph_vec_env
from sb3_hgrn.envs import uav_mbs_v0

parser = argparse.ArgumentParser()
parser.add_argument("--uavs", type=int, default=10)
parser.add_argument("--users", type=int, default=60, help="ground users, in 3 clusters")
parser.add_argument("--observation", choices=["compact", "raster"], default="compact")
parser.add_argument("--max-cycles", type=int, default=100, help="steps per episode")
parser.add_argument("--copies", type=int, default=4, help="env copies stepped together")
parser.add_argument("--timesteps", type=int, default=400_000, help="agent-steps of training")
parser.add_argument("--buffer-size", type=int, default=200_000, help="replay agent-transitions")
parser.add_argument("--eval-episodes", type=int, default=16, help="team episodes per evaluation")
parser.add_argument("--seed", type=int, default=0)
parser.add_argument("--save", default="soft_hgrn_uav_mbs.zip")
args = parser.parse_args()

env_kwargs = dict(
    n_uavs=args.uavs, n_users=args.users, max_cycles=args.max_cycles, observation_mode=args.observation
)
env = make_graph_vec_env(uav_mbs_v0.parallel_env, n_envs=args.copies, seed=args.seed, env_kwargs=env_kwargs)
eval_env = make_graph_vec_env(
    uav_mbs_v0.parallel_env, n_envs=args.copies, seed=args.seed + 1000, env_kwargs=env_kwargs
)
print(f"{env.n_agents} UAVs and {args.users} users per copy, {args.observation} observations")


class HoverPolicy:
    def predict(self, obs, state=None, episode_start=None, deterministic=False):
        return np.full(len(obs["obs"]), 16), state


for name, policy in (("random", RandomGraphPolicy(eval_env, seed=args.seed)), ("hover", HoverPolicy())):
    mean_return, std_return = evaluate_graph_policy(policy, eval_env, n_eval_episodes=args.eval_episodes)
    print(f"{name + ' policy:':15s}team return {mean_return:.1f} +/- {std_return:.1f}")

model = SoftHGRN("GraphPolicy", env, buffer_size=args.buffer_size, seed=args.seed, verbose=1)
start = time.time()
model.learn(total_timesteps=args.timesteps, log_interval=20)  # logs every 20 team episodes
steps = model.num_timesteps
print(f"trained {steps} agent-steps ({steps // env.num_envs} env steps) in {time.time() - start:.0f} s")
model.save(args.save)

mean_return, std_return = evaluate_graph_policy(model, eval_env, n_eval_episodes=args.eval_episodes)
print(f"{'Soft-HGRN:':15s}team return {mean_return:.1f} +/- {std_return:.1f}  (saved {args.save})")
