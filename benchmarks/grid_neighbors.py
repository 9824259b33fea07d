"""Dense against blocked neighbour lists of agents on grid cells: where ``DENSE_MAX_AGENTS`` belongs.

Run: python benchmarks/grid_neighbors.py [--agents 100 128 140 180 256 512] [--calls 200] [--repeats 7]

For each agent count N the agents stand on random cells of a square whose side gives about 6 other
agents within Chebyshev radius 3 (the density of Surviving's paper map), and both ways
:func:`sb3_hgrn.envs.graph.grid_neighbors` can build the lists (9 entries per row) are timed: one
``(N, N)`` matrix of int32 sort keys sorted row by row, and the blocked search of the 3 x 3 blocks
around each agent. It checks that both give the same lists and prints microseconds per graph, best of
``--repeats`` rounds of ``--calls`` graphs.
"""

from __future__ import annotations

import argparse
import math
import time
from collections.abc import Callable

import numpy as np

from sb3_hgrn.envs import graph

RADIUS, WIDTH = 3, 9


def best_microseconds(build: Callable[[], np.ndarray], calls: int, repeats: int) -> float:
    """Best time of one ``build()`` in microseconds over ``repeats`` rounds of ``calls`` calls."""
    best = math.inf
    for _ in range(repeats):
        start = time.perf_counter()
        for _ in range(calls):
            build()
        best = min(best, (time.perf_counter() - start) / calls)
    return best * 1e6


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--agents", type=int, nargs="+", default=[100, 128, 140, 180, 256, 512])
    parser.add_argument("--calls", type=int, default=200)
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    print(f"DENSE_MAX_AGENTS = {graph.DENSE_MAX_AGENTS}")
    print("| agents | dense (us) | blocked (us) |")
    print("|---:|---:|---:|")
    for n_agents in args.agents:
        side = max(3, int(math.sqrt(n_agents * (2 * RADIUS + 1) ** 2 / 6)))
        cells = rng.integers(0, side, size=(n_agents, 2))
        wide = cells.astype(np.int64)

        def dense(cells=cells):
            return graph._dense_neighbors(cells, 0, RADIUS, WIDTH, "chebyshev")

        def blocked(wide=wide):
            return graph._blocked_neighbors(wide, RADIUS, WIDTH, "chebyshev")

        if not np.array_equal(dense(), blocked()):
            raise SystemExit(f"dense and blocked lists differ at {n_agents} agents")
        times = [best_microseconds(build, args.calls, args.repeats) for build in (dense, blocked)]
        print(f"| {n_agents} | {times[0]:.0f} | {times[1]:.0f} |", flush=True)


if __name__ == "__main__":
    main()
