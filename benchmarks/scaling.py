"""Cost per agent-step of Soft-HGRN on Surviving as the number of agents grows.

Run: python benchmarks/scaling.py [--agents 100 200 500 1000] [--threads 2]

The map grows with the agent count so that the density stays that of the paper's map (100 agents on
32 x 32): side ``round(32 * sqrt(N / 100))`` (32, 45, 72, 101 cells for 100, 200, 500, 1,000 agents)
and ``round(8 * N / 100)`` resource points, so every agent has about as many neighbours at every N.
(Wider maps need more bits for the coordinates: observations have 39 entries at 32 x 32, 41 at 45 x 45
and 43 at 72 x 72 and 101 x 101.)

For every agent count N it measures, with one env copy:
- env steps/s of the array API with the graph (``step_arrays`` and ``neighbors``, random actions);
- collection steps/s with a SoftHGRN policy (policy forward, env step, replay add; no training);
- the time of one ``SoftHGRN.train`` update at the default network size on a fixed number of graphs
  (``--graphs``, 8 by default), so one update covers ``graphs * N`` agent-steps;
- replay memory per buffer row (one joint transition of all N agents).

It prints a Markdown table of these costs per agent-step and the ratio of each to its value at the
smallest N (the target is at most 1.5x at 1,000 agents against 100). Timings are the best of
repeated runs (:func:`throughput.best_rate`).
"""

from __future__ import annotations

import argparse
import math
import os
from typing import NamedTuple

import numpy as np
import torch as th
from throughput import best_rate

from sb3_hgrn import SoftHGRN, make_graph_vec_env
from sb3_hgrn.envs import surviving_v0

REFERENCE_AGENTS = 100
REFERENCE_MAP_SIZE = 32
REFERENCE_RESOURCES = 8


class Costs(NamedTuple):
    """Measured costs at one agent count."""

    n_agents: int
    map_size: int
    n_resources: int
    env_rate: float  # env steps/s (all agents)
    collect_rate: float  # vec-steps/s of collection (all agents)
    update_seconds: float  # one gradient update on `graphs` graphs
    row_bytes: float  # replay bytes per joint transition


def scaled_env_kwargs(n_agents: int) -> dict[str, int]:
    """Surviving arguments for ``n_agents`` agents at the density of 100 agents on 32 x 32."""
    scale = n_agents / REFERENCE_AGENTS
    return {
        "n_agents": n_agents,
        "map_size": round(REFERENCE_MAP_SIZE * math.sqrt(scale)),
        "n_resources": max(1, round(REFERENCE_RESOURCES * scale)),
    }


def env_rate(env_kwargs: dict[str, int], steps: int) -> float:
    """Env steps/s of the array API with the graph, random actions."""
    env = surviving_v0.parallel_env(**env_kwargs, max_cycles=10**9)
    env.reset_arrays(seed=0)
    actions = np.random.default_rng(0).integers(0, surviving_v0.N_ACTIONS, size=(steps, env.n_agents))

    def run() -> None:
        for step_actions in actions:
            env.step_arrays(step_actions)
            env.neighbors()

    return best_rate(run, steps)


def model_costs(
    env_kwargs: dict[str, int], collect_steps: int, graphs: int, updates: int
) -> tuple[float, float, float]:
    """Collection vec-steps/s, seconds per update of ``graphs`` graphs and replay bytes per row.

    The collection runs fill the replay buffer that the updates then sample from.
    """
    env = make_graph_vec_env("surviving_v0", n_envs=1, seed=0, env_kwargs=env_kwargs)
    model = SoftHGRN("GraphPolicy", env, learning_starts=10**9, batch_size=graphs, seed=0)  # no training
    model.learn(env.num_envs * 10)  # warm-up
    total = collect_steps * env.num_envs
    collect = best_rate(lambda: model.learn(total), collect_steps)
    model.train(gradient_steps=1, batch_size=graphs)  # warm-up
    update_rate = best_rate(lambda: model.train(gradient_steps=updates, batch_size=graphs), updates)
    buffer = model.replay_buffer
    return collect, 1.0 / update_rate, buffer.nbytes / buffer.buffer_size


def measure(n_agents: int, agent_steps: int, graphs: int, updates: int) -> Costs:
    """All costs at ``n_agents``; env and collection runs last about ``agent_steps`` agent-steps."""
    env_kwargs = scaled_env_kwargs(n_agents)
    steps = max(agent_steps // n_agents, 10)
    rate = env_rate(env_kwargs, 10 * steps)  # the env alone is about 10 times faster than collection
    collect, update_seconds, row_bytes = model_costs(env_kwargs, steps, graphs, updates)
    return Costs(n_agents, env_kwargs["map_size"], env_kwargs["n_resources"], rate, collect,
                 update_seconds, row_bytes)  # fmt: skip


def per_agent_step(costs: Costs, graphs: int) -> np.ndarray:
    """Env, collection and update microseconds per agent-step and replay bytes per agent-transition."""
    n = costs.n_agents
    return np.array([
        1e6 / (costs.env_rate * n),
        1e6 / (costs.collect_rate * n),
        1e6 * costs.update_seconds / (graphs * n),
        costs.row_bytes / n,
    ])  # fmt: skip


def print_table(results: list[Costs], graphs: int) -> None:
    """Markdown table of per-agent-step costs, each with its ratio to the first row's."""
    reference = per_agent_step(results[0], graphs)
    print(
        f"| agents | map | resources | env steps/s | env us/agent-step | collect steps/s "
        f"| collect us/agent-step | update s ({graphs} graphs) | update us/agent-step "
        f"| replay B/row | replay B/agent-transition |"
    )
    print("|" + "---:|" * 11)
    for costs in results:
        per_agent = per_agent_step(costs, graphs)
        ratio = per_agent / reference
        print(
            f"| {costs.n_agents} | {costs.map_size} x {costs.map_size} | {costs.n_resources} "
            f"| {costs.env_rate:,.0f} | {per_agent[0]:.2f} ({ratio[0]:.2f}x) "
            f"| {costs.collect_rate:,.1f} | {per_agent[1]:.1f} ({ratio[1]:.2f}x) "
            f"| {costs.update_seconds:.3f} | {per_agent[2]:.2f} ({ratio[2]:.2f}x) "
            f"| {costs.row_bytes:,.0f} | {per_agent[3]:.0f} ({ratio[3]:.2f}x) |"
        )
    print(
        f"\n(x): cost per agent-step (bytes per agent-transition) relative to {results[0].n_agents} agents; "
        "target <= 1.5x at 1,000 agents."
    )


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--agents", nargs="+", type=int, default=[100, 200, 500, 1000])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--graphs", type=int, default=8, help="graphs per gradient update")
    parser.add_argument("--updates", type=int, default=10, help="gradient updates per timing")
    parser.add_argument(
        "--agent-steps", type=int, default=50_000, help="agent-steps per collection timing (10x for the env)"
    )
    args = parser.parse_args()
    th.set_num_threads(args.threads)
    print(
        f"Surviving at the density of {REFERENCE_AGENTS} agents on {REFERENCE_MAP_SIZE} x "
        f"{REFERENCE_MAP_SIZE}, torch {th.__version__}, {args.threads} threads, "
        f"load average at start {os.getloadavg()[0]:.2f}\n"
    )
    results = []
    for n_agents in sorted(args.agents):
        results.append(measure(n_agents, args.agent_steps, args.graphs, args.updates))
    print_table(results, args.graphs)


if __name__ == "__main__":
    main()
