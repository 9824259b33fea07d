"""Train Soft-HGRN on Cooperative Treasure Collection (three agent groups), compare it with a random
policy and save the model.

Small default (hunters, red and blue banks on a 20 x 20 map; a few minutes on 2 CPU cores):
    python examples/train_ctc.py
Homogeneous attention only (every group attends within itself, the paper's "Soft-DGRN"):
    python examples/train_ctc.py --communication gat
The paper's map (20 hunters, 10 + 10 banks, 40 x 40, 500-step episodes):
    python examples/train_ctc.py --hunters 20 --banks 10 --map-size 40 --max-cycles 500 --copies 1 \
        --timesteps 5000000
"""

import argparse
import time

from sb3_hgrn import RandomGraphPolicy, SoftHGRN, evaluate_graph_policy, make_graph_vec_env

parser = argparse.ArgumentParser()
parser.add_argument("--hunters", type=int, default=8)
parser.add_argument("--banks", type=int, default=4, help="red banks, and as many blue banks")
parser.add_argument("--resources", type=int, default=2, help="resource points of each colour")
parser.add_argument("--map-size", type=int, default=20, help="including the 3-cell wall ring")
parser.add_argument("--max-cycles", type=int, default=100, help="steps per episode")
parser.add_argument("--communication", choices=["hgat", "gat"], default="hgat")
parser.add_argument("--copies", type=int, default=4, help="env copies stepped together")
parser.add_argument("--timesteps", type=int, default=400_000, help="agent-steps of training")
parser.add_argument("--eval-episodes", type=int, default=8, help="team episodes per evaluation")
parser.add_argument("--seed", type=int, default=0)
parser.add_argument("--save", default="soft_hgrn_ctc.zip")
args = parser.parse_args()

env_kwargs = dict(
    n_hunters=args.hunters,
    n_red_banks=args.banks,
    n_blue_banks=args.banks,
    n_red_resources=args.resources,
    n_blue_resources=args.resources,
    map_size=args.map_size,
    max_cycles=args.max_cycles,
)
env = make_graph_vec_env("ctc_v0", n_envs=args.copies, seed=args.seed, env_kwargs=env_kwargs)
eval_env = make_graph_vec_env("ctc_v0", n_envs=args.copies, seed=args.seed + 1000, env_kwargs=env_kwargs)

random_return, random_std = evaluate_graph_policy(
    RandomGraphPolicy(eval_env, seed=args.seed), eval_env, n_eval_episodes=args.eval_episodes
)
print(f"random policy: team return {random_return:.1f} +/- {random_std:.1f}")

model = SoftHGRN(
    "GraphPolicy", env, policy_kwargs=dict(communication=args.communication), seed=args.seed, verbose=1
)
start = time.time()
model.learn(total_timesteps=args.timesteps, log_interval=20)  # logs every 20 team episodes
steps = model.num_timesteps
print(f"trained {steps} agent-steps ({steps // env.num_envs} env steps) in {time.time() - start:.0f} s")
model.save(args.save)

mean_return, std_return = evaluate_graph_policy(model, eval_env, n_eval_episodes=args.eval_episodes)
print(f"Soft-HGRN ({args.communication}): team return {mean_return:.1f} +/- {std_return:.1f}")
