"""``torch.compile`` as a candidate for the network: the library's HGRN (sparse CSR attention, eager)
against the same network with its attention written as gathers, eager and compiled.

Run: python benchmarks/compiled_network.py [--agents 100] [--neighbors 16] [--batch 32]
     [--hidden 64] [--threads 1] [--repeats 5]

``torch.compile`` cannot trace the CSR kernel (sparse layouts, a custom autograd function), so the
compiled form gathers every entry's keys and values (``(rows, E, heads, head_dim)``) and takes a
masked softmax over the entries, over the same canonical entries (:class:`GraphBatch`'s ``columns``
and ``mask``). Both forms share one network's parameters (one agent group, graph attention), and
the script checks that their outputs agree before timing:

- acting: one graph, no gradients (``torch.inference_mode``), the whole network's forward;
- training: ``--batch`` graphs, the forward and the backward of a loss on its outputs.

It prints the best mean of ``--repeats`` timings in milliseconds, the compile time, and the number
of calls after which the compiled form has paid back its compile time.
"""

from __future__ import annotations

import argparse
import math
import time
from collections.abc import Callable

import torch
import torch.nn.functional as F
from torch import Tensor

from sb3_hgrn.common.attention import GraphBatch
from sb3_hgrn.common.hgrn import HGRN, GraphAttention

OBS_DIM, N_ACTIONS = 50, 5


def gathered_attention(layer: GraphAttention, x: Tensor, columns: Tensor, mask: Tensor) -> Tensor:
    """``layer`` on ``x`` ``(rows, in_dim)`` with keys and values gathered per entry ``(rows, E)``."""
    heads, dim = layer.n_heads, layer.head_dim
    query, key, value = (
        F.relu(part[0](x)).view(-1, heads, dim) for part in (layer.query, layer.key, layer.value)
    )
    keys, values = key[columns], value[columns]  # (rows, E, heads, dim)
    logits = (query.unsqueeze(1) * keys).sum(-1) * dim**-0.5
    weights = logits.masked_fill(~mask.unsqueeze(-1), -math.inf).softmax(dim=1)
    mixed = (weights.unsqueeze(-1) * values).sum(1).reshape(x.shape[0], heads * dim)
    return F.relu(layer.output[0](mixed))


def gathered_forward(net: HGRN, obs: Tensor, columns: Tensor, mask: Tensor, hidden: Tensor) -> Tensor:
    """The outputs ``(rows, n_actions)`` of ``net`` (one group, graph attention) in gather form."""
    encoded = net.encoder[0](obs.reshape(-1, net.obs_dim))
    hop1 = gathered_attention(net.comm1, encoded, columns, mask)
    hop2 = gathered_attention(net.comm2, hop1, columns, mask)
    memory = net.gru[0](torch.cat([encoded, hop1, hop2], dim=-1), hidden.reshape(-1, net.hidden_dim))
    return net.head[0](memory)


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
    """Time the three forms on ``batch`` random graphs and print one line."""
    generator = torch.Generator().manual_seed(0)
    net = HGRN(OBS_DIM, N_ACTIONS, hidden_dim=args.hidden)
    obs = torch.randn(batch, args.agents, OBS_DIM, generator=generator)
    hidden = torch.randn(batch, args.agents, args.hidden, generator=generator)
    neighbors = torch.randint(-1, args.agents, (batch, args.agents, args.neighbors), generator=generator)
    compiled = torch.compile(gathered_forward)

    def sparse() -> Tensor:
        return net(obs, GraphBatch(neighbors), hidden)[0].reshape(-1, N_ACTIONS)

    def gathered(form: Callable) -> Callable[[], Tensor]:
        def run() -> Tensor:
            graph = GraphBatch(neighbors)
            return form(net, obs, graph.columns, graph.mask, hidden)

        return run

    def timed(run: Callable[[], Tensor]) -> Callable[[], None]:
        def step() -> None:
            if train:
                net.zero_grad(set_to_none=True)
                run().square().mean().backward()
            else:
                with torch.inference_mode():
                    run()

        return step

    with torch.inference_mode():
        difference = (gathered(gathered_forward)() - sparse()).abs().max().item()
    start = time.perf_counter()
    timed(gathered(compiled))()
    compile_s = time.perf_counter() - start
    calls = 10 if train else 100
    eager, gather, fused = (
        best_ms(timed(run), args.repeats, calls)
        for run in (sparse, gathered(gathered_forward), gathered(compiled))
    )
    payback = math.ceil(1000 * compile_s / (eager - fused)) if fused < eager else None
    print(
        f"| {name} | {batch} | {eager:.2f} | {gather:.2f} | {fused:.2f} | {compile_s:.1f} | "
        f"{payback if payback is not None else 'never'} | {difference:.1e} |",
        flush=True,
    )


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
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
        "| pass | graphs | CSR, eager (ms) | gather, eager (ms) | gather, compiled (ms) | compile (s) "
        "| calls to pay back | max output difference |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    compare("acting", 1, False, args)
    compare("training", args.batch, True, args)


if __name__ == "__main__":
    main()
