"""Time to build the communication graph of ``GraphFromPositions`` from float positions.

Run: python benchmarks/graph_from_positions.py [--agents 100 1000 10000] [--dim 2] [--calls 10] [--repeats 7]

Agents stand uniformly at random in a square (a cube for ``--dim 3``) of side ``N ** (1 / dim)``, one
agent per unit area (volume), so every agent has about as many agents near it at every N. For each N
it times :meth:`PositionGraph.neighbors` (KD-tree build and queries, the reordering to self-first
rows) in three modes: ``k=8`` nearest neighbours; all agents within radius 1.6 (about 8 in range), at
most 16 listed; and ``k=8`` on a torus of the same side. Times are the CPU time of this process (one
thread), best of ``--repeats`` runs of ``--calls`` graphs each on one draw of positions per mode and
N, so other jobs on the machine slow them little. It prints a Markdown table of milliseconds per
graph, microseconds per agent with its ratio to the value at the smallest N, and the mean number of
neighbours listed.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from sb3_hgrn.envs.position_graph import PositionGraph

RADIUS, RADIUS_WIDTH, K = 1.6, 16, 8


def graphs(n_agents: int, side: float) -> dict[str, PositionGraph]:
    """The timed modes at ``n_agents`` agents in a world of side ``side``."""
    return {
        f"k={K}": PositionGraph(n_agents, k=K),
        f"radius {RADIUS}, max_neighbors={RADIUS_WIDTH}": PositionGraph(
            n_agents, radius=RADIUS, max_neighbors=RADIUS_WIDTH
        ),
        f"k={K}, torus": PositionGraph(n_agents, k=K, world_size=side),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--agents", type=int, nargs="+", default=[100, 1000, 10000])
    parser.add_argument("--dim", type=int, default=2)
    parser.add_argument("--calls", type=int, default=10)
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    print("| mode | agents | ms per graph | us per agent | per-agent cost vs first N | mean neighbours |")
    print("|---|---:|---:|---:|---:|---:|")
    baseline: dict[str, float] = {}
    rows = []
    for n_agents in args.agents:
        side = n_agents ** (1 / args.dim)
        for mode, graph in graphs(n_agents, side).items():
            points = rng.random((n_agents, args.dim)) * side
            seconds = cpu_seconds_per_graph(graph, points, args.calls, args.repeats)
            per_agent = seconds / n_agents * 1e6
            baseline.setdefault(mode, per_agent)
            neighbours = (graph.neighbors(points) >= 0).sum(axis=1).mean() - 1
            rows.append((mode, n_agents, seconds * 1e3, per_agent, per_agent / baseline[mode], neighbours))
    for mode, n_agents, ms, per_agent, ratio, neighbours in sorted(rows, key=lambda row: row[0]):
        print(f"| {mode} | {n_agents:,} | {ms:.3f} | {per_agent:.2f} | {ratio:.2f}x | {neighbours:.1f} |")


def cpu_seconds_per_graph(graph: PositionGraph, points: np.ndarray, calls: int, repeats: int) -> float:
    """Least process CPU time per ``graph.neighbors(points)`` call over ``repeats`` runs of ``calls``."""
    best = float("inf")
    for _ in range(repeats):
        start = time.process_time()
        for _ in range(calls):
            graph.neighbors(points)
        best = min(best, (time.process_time() - start) / calls)
    return best


if __name__ == "__main__":
    main()
