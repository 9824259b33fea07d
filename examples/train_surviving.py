"""Train Soft-HGRN on Surviving, compare it with a random policy and save the model.

Small default (a few minutes on 2 CPU cores): python examples/train_surviving.py
The paper's map (100 agents, 32 x 32, 500-step episodes):
    python examples/train_surviving.py --agents 100 --map-size 32 --resources 8 --max-cycles 500 --copies 1 \
        --timesteps 6000000
"""

import argparse
import time

from sb3_hgrn import RandomGraphPolicy, SoftHGRN, evaluate_graph_policy, make_graph_vec_env

parser = argparse.ArgumentParser()
parser.add_argument("--agents", type=int, default=20)
parser.add_argument("--map-size", type=int, default=16)
parser.add_argument("--resources", type=int, default=3)
parser.add_argument("--max-cycles", type=int, default=100, help="steps per episode")
parser.add_argument("--copies", type=int, default=4, help="env copies stepped together")
parser.add_argument("--timesteps", type=int, default=400_000, help="agent-steps of training")
parser.add_argument("--eval-episodes", type=int, default=8, help="team episodes per evaluation")
parser.add_argument("--seed", type=int, default=0)
parser.add_argument("--save", default="soft_hgrn_surviving.zip")
args = parser.parse_args()

env_kwargs = dict(
    n_agents=args.agents, map_size=args.map_size, n_resources=args.resources, max_cycles=args.max_cycles
)
env = make_graph_vec_env("surviving_v0", n_envs=args.copies, seed=args.seed, env_kwargs=env_kwargs)
eval_env = make_graph_vec_env(
    "surviving_v0", n_envs=args.copies, seed=args.seed + 1000, env_kwargs=env_kwargs
)


random_return, random_std = evaluate_graph_policy(
    RandomGraphPolicy(eval_env, seed=args.seed), eval_env, n_eval_episodes=args.eval_episodes
)
print(f"random policy: team return {random_return:.1f} +/- {random_std:.1f}")

model = SoftHGRN("GraphPolicy", env, seed=args.seed, verbose=1)
start = time.time()
model.learn(total_timesteps=args.timesteps, log_interval=20)  # logs every 20 team episodes
steps = model.num_timesteps
print(f"trained {steps} agent-steps ({steps // env.num_envs} env steps) in {time.time() - start:.0f} s")
model.save(args.save)

mean_return, std_return = evaluate_graph_policy(model, eval_env, n_eval_episodes=args.eval_episodes)
print(f"Soft-HGRN:     team return {mean_return:.1f} +/- {std_return:.1f}  (saved {args.save})")
