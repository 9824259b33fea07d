"""Train Soft-HGRN predators on Pursuit (MAgent2), compare them with random predators and save the model.

Needs MAgent2 (pip install magent2==0.3.4). The prey are scripted evaders unless --prey random.
Small default (a couple of minutes on 2 CPU cores): python examples/train_pursuit.py
The paper's map (25 predators against 50 prey, 45 x 45, 500-step episodes):
    python examples/train_pursuit.py --map-size 45 --max-cycles 500 --copies 1 --timesteps 5000000
"""

import argparse
import time

from sb3_hgrn import RandomGraphPolicy, SoftHGRN, evaluate_graph_policy, make_graph_vec_env
from sb3_hgrn.envs import pursuit_v0

parser = argparse.ArgumentParser()
parser.add_argument("--map-size", type=int, default=20, help="20: 5 predators, 10 prey; 45: 25 and 50")
parser.add_argument("--max-cycles", type=int, default=100, help="steps per episode")
parser.add_argument("--prey", choices=["evader", "random"], default="evader", help="prey controller")
parser.add_argument("--copies", type=int, default=4, help="env copies stepped together")
parser.add_argument("--timesteps", type=int, default=200_000, help="agent-steps of training")
parser.add_argument(
    "--buffer-size", type=int, default=200_000, help="replay agent-transitions (~1.2 kB each)"
)
parser.add_argument("--eval-episodes", type=int, default=8, help="team episodes per evaluation")
parser.add_argument("--seed", type=int, default=0)
parser.add_argument("--save", default="soft_hgrn_pursuit.zip")
args = parser.parse_args()

env_kwargs = dict(map_size=args.map_size, max_cycles=args.max_cycles, prey_controller=args.prey)
env = make_graph_vec_env(pursuit_v0.parallel_env, n_envs=args.copies, seed=args.seed, env_kwargs=env_kwargs)
eval_env = make_graph_vec_env(
    pursuit_v0.parallel_env, n_envs=args.copies, seed=args.seed + 1000, env_kwargs=env_kwargs
)
print(f"{env.n_agents} predators per copy, {args.prey} prey, map {args.map_size} x {args.map_size}")


random_return, random_std = evaluate_graph_policy(
    RandomGraphPolicy(eval_env, seed=args.seed), eval_env, n_eval_episodes=args.eval_episodes
)
print(f"random predators: team return {random_return:.1f} +/- {random_std:.1f}")

model = SoftHGRN("GraphPolicy", env, buffer_size=args.buffer_size, seed=args.seed, verbose=1)
start = time.time()
model.learn(total_timesteps=args.timesteps, log_interval=20)  # logs every 20 team episodes
steps = model.num_timesteps
print(f"trained {steps} agent-steps ({steps // env.num_envs} env steps) in {time.time() - start:.0f} s")
model.save(args.save)

mean_return, std_return = evaluate_graph_policy(model, eval_env, n_eval_episodes=args.eval_episodes)
print(f"Soft-HGRN:        team return {mean_return:.1f} +/- {std_return:.1f}  (saved {args.save})")
