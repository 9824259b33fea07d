"""``compile_network``: the HGRN with its sparse attention kernel (eager) against the same network in
gather form (``HGRN(compile_network=...)``), run by dynamo without compiling and compiled.

Run: python benchmarks/compiled_network.py [--agents 100] [--neighbors 16] [--batch 32]
     [--hidden 64] [--threads 1] [--repeats 5]

The three networks share one set of parameters (one agent group, graph attention), and the script
checks that their outputs agree before timing:

- acting: one graph, no gradients (``torch.inference_mode``), the whole network's forward;
- training: ``--batch`` graphs, the forward and the backward of a loss on its outputs.

Every call builds its ``GraphBatch``, as acting and training do. The script prints the best mean of
``--repeats`` timings in milliseconds, the seconds the first compiled call took (the compilation; less
where torch's on-disk cache holds an earlier run's code), and the number of calls after which the
compiled form has paid that back.
"""

from __future__ import annotations

import argparse
import math
import time
from collections.abc import Callable

import torch
from torch import Tensor

from sb3_hgrn.common.attention import GraphBatch
from sb3_hgrn.common.hgrn import HGRN

OBS_DIM, N_ACTIONS = 50, 5


def best_ms(step: Callable[[], object], repeats: int, calls: int) -> float:
    """Best mean time of ``calls`` calls of ``step`` in milliseconds over ``repeats`` timings."""
    for _ in range(3):
        step()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        for _ in range(calls):
            step()
        times.append((time.perf_counter() - start) / calls)
    return 1000 * min(times)


def compare(name: str, batch: int, train: bool, args: argparse.Namespace) -> None:
    """Time the three forms on ``batch`` random graphs and print one table row."""
    generator = torch.Generator().manual_seed(0)
    sparse = HGRN(OBS_DIM, N_ACTIONS, hidden_dim=args.hidden)
    gathered = HGRN(OBS_DIM, N_ACTIONS, hidden_dim=args.hidden, compile_network={"backend": "eager"})
    compiled = HGRN(OBS_DIM, N_ACTIONS, hidden_dim=args.hidden, compile_network=True)
    for network in (gathered, compiled):
        network.load_state_dict(sparse.state_dict())
    obs = torch.randn(batch, args.agents, OBS_DIM, generator=generator)
    hidden = torch.randn(batch, args.agents, args.hidden, generator=generator)
    neighbors = torch.randint(-1, args.agents, (batch, args.agents, args.neighbors), generator=generator)

    def step(network: HGRN) -> Callable[[], Tensor]:
        def run() -> Tensor:
            if not train:
                with torch.inference_mode():
                    return network(obs, GraphBatch(neighbors), hidden)[0]
            network.zero_grad(set_to_none=True)
            outputs = network(obs, GraphBatch(neighbors), hidden)[0]
            outputs.square().mean().backward()
            return outputs.detach()

        return run

    start = time.perf_counter()
    compiled_outputs = step(compiled)()
    compile_s = time.perf_counter() - start
    difference = (compiled_outputs - step(sparse)()).abs().max().item()
    calls = 10 if train else 100
    eager_ms, gathered_ms, compiled_ms = (
        best_ms(step(network), args.repeats, calls) for network in (sparse, gathered, compiled)
    )
    payback = math.ceil(1000 * compile_s / (eager_ms - compiled_ms)) if compiled_ms < eager_ms else "never"
    print(
        f"| {name} | {batch} | {eager_ms:.2f} | {gathered_ms:.2f} | {compiled_ms:.2f} | {compile_s:.1f} | "
        f"{payback} | {difference:.1e} |",
        flush=True,
    )


def main() -> None:
    formatter = argparse.RawDescriptionHelpFormatter
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=formatter)
    parser.add_argument("--agents", type=int, default=100)
    parser.add_argument("--neighbors", type=int, default=16)
    parser.add_argument("--batch", type=int, default=32, help="graphs per training batch")
    parser.add_argument("--hidden", type=int, default=64)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    print(
        f"HGRN hidden {args.hidden}, {args.agents} agents, {args.neighbors} neighbours, "
        f"torch {torch.__version__}, {args.threads} thread(s)"
    )
    print(
        "| pass | graphs | sparse kernel, eager (ms) | gather form, uncompiled (ms) "
        "| gather form, compiled (ms) | compilation (s) | calls to pay back | max output difference |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    compare("acting", 1, False, args)
    compare("training", args.batch, True, args)


if __name__ == "__main__":
    main()
