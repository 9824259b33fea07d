"""The library's CSR attention kernel against gather-based attention over the same neighbour lists.

Run: python benchmarks/attention_kernels.py [--batches 1 32 128] [--agents 100] [--neighbors 16]
     [--heads 4] [--head-dim 16] [--threads 1]

For each batch of random graphs it times one forward and backward pass of multi-head attention over
the neighbour lists (``(batch * agents, heads, head_dim)`` queries, keys and values, loss = sum of the
outputs) with :class:`sb3_hgrn.common.attention.NeighborAttention` (sparse CSR products) and with two
gather forms that copy every agent's keys and values per entry (``(rows, E, heads, head_dim)``): an
einsum over advanced indexing, and ``index_select`` with batched matrix products. It prints the best
of ``--repeats`` times in milliseconds and the largest difference of the gradients from the kernel's.

A second table times the forward pass alone under ``torch.inference_mode`` (acting, the target
network): the kernel through its autograd function and the bare computation that
:func:`~sb3_hgrn.common.attention.neighbor_attention` runs when no gradient is recorded.
"""

from __future__ import annotations

import argparse
import math
import time
from collections.abc import Callable

import torch

from sb3_hgrn.common.attention import GraphBatch, NeighborAttention, neighbor_attention


def best_ms(step: Callable[[], None], repeats: int) -> float:
    """Best time of ``step()`` in milliseconds over ``repeats`` calls, after two warm-up calls."""
    for _ in range(2):
        step()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        step()
        times.append(time.perf_counter() - start)
    return 1000 * min(times)


def gather_einsum(query, key, value, columns, mask):
    """Attention with keys and values gathered per entry by advanced indexing; ``(rows, heads, dim)``."""
    logits = torch.einsum("rhd,rehd->rhe", query * query.shape[-1] ** -0.5, key[columns])
    weights = logits.masked_fill(~mask.unsqueeze(1), -math.inf).softmax(-1)
    return torch.einsum("rhe,rehd->rhd", weights, value[columns])


def gather_bmm(query, key, value, columns, mask):
    """Attention with keys and values gathered by ``index_select`` and batched matrix products."""
    rows, heads, dim = query.shape
    entries = columns.shape[1]
    flat = columns.reshape(-1)
    keys = key.index_select(0, flat).view(rows, entries, heads, dim).transpose(1, 2)
    values = value.index_select(0, flat).view(rows, entries, heads, dim).transpose(1, 2)
    logits = torch.matmul(keys, (query * dim**-0.5).unsqueeze(-1)).squeeze(-1)
    weights = logits.masked_fill(~mask.unsqueeze(1), -math.inf).softmax(-1)
    return torch.matmul(weights.unsqueeze(-2), values).squeeze(-2)


def compare(batch: int, args: argparse.Namespace, generator: torch.Generator) -> str:
    """One table row: the three kernels' times and gradient difference on ``batch`` random graphs."""
    neighbors = torch.randint(-1, args.agents, (batch, args.agents, args.neighbors), generator=generator)
    graphs = GraphBatch(neighbors)
    shape = (batch * args.agents, args.heads, args.head_dim)
    inputs = [torch.randn(shape, generator=generator).requires_grad_() for _ in range(3)]
    pattern, segments = graphs.pattern(args.heads), graphs.segments(False)
    kernels = {
        "csr": lambda q, k, v: NeighborAttention.apply(q, k, v, pattern, segments)[0],
        "einsum": lambda q, k, v: gather_einsum(q, k, v, graphs.columns, graphs.mask),
        "bmm": lambda q, k, v: gather_bmm(q, k, v, graphs.columns, graphs.mask),
    }

    def gradients(name: str) -> list[torch.Tensor]:
        for tensor in inputs:
            tensor.grad = None
        kernels[name](*inputs).sum().backward()
        return [tensor.grad for tensor in inputs]

    times = [best_ms(lambda name=name: gradients(name), args.repeats) for name in kernels]
    reference = gradients("csr")
    difference = max(
        (mine - theirs).abs().max().item()
        for name in ("einsum", "bmm")
        for mine, theirs in zip(gradients(name), reference, strict=True)
    )
    return f"| {batch} | " + " | ".join(f"{ms:.2f}" for ms in times) + f" | {difference:.1e} |"


def compare_without_grad(batch: int, args: argparse.Namespace, generator: torch.Generator) -> str:
    """One row of the forward-only table: the autograd function against the bare computation."""
    neighbors = torch.randint(-1, args.agents, (batch, args.agents, args.neighbors), generator=generator)
    graphs = GraphBatch(neighbors)
    query, key, value = (
        torch.randn(batch * args.agents, args.heads, args.head_dim, generator=generator) for _ in range(3)
    )
    pattern, segments = graphs.pattern(args.heads), graphs.segments(False)
    with torch.inference_mode():
        through_function = best_ms(
            lambda: NeighborAttention.apply(query, key, value, pattern, segments), args.repeats
        )
        bare = best_ms(lambda: neighbor_attention(query, key, value, pattern, segments), args.repeats)
    return f"| {batch} | {through_function:.3f} | {bare:.3f} |"


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--batches", nargs="+", type=int, default=[1, 32, 128])
    parser.add_argument("--agents", type=int, default=100)
    parser.add_argument("--neighbors", type=int, default=16)
    parser.add_argument("--heads", type=int, default=4)
    parser.add_argument("--head-dim", type=int, default=16)
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    generator = torch.Generator().manual_seed(0)
    print(f"{args.agents} agents, {args.neighbors} neighbours, {args.heads} heads x {args.head_dim}, "
          f"{args.threads} thread(s); forward + backward, best of {args.repeats}")  # fmt: skip
    print("| graphs | CSR kernel (ms) | gather, einsum (ms) | gather, bmm (ms) | max gradient difference |")
    print("|---:|---:|---:|---:|---:|")
    for batch in args.batches:
        print(compare(batch, args, generator), flush=True)
    print("\nForward only, no gradient recorded (torch.inference_mode)")
    print("| graphs | autograd function (ms) | bare computation (ms) |")
    print("|---:|---:|---:|")
    for batch in args.batches:
        print(compare_without_grad(batch, args, generator), flush=True)


if __name__ == "__main__":
    main()
