"""Twin critics run one after the other (as DiscreteSAC runs them) against stacked into batched products.

Run: python benchmarks/twin_critics.py [--threads 1] [--repeats 5]

For each case (observation size, hidden layers, actions, batch: those of CartPole's, MountainCar's
and LunarLander's settings in ``sb3_hgrn/hyperparams/discrete_sac.yml``) it times one forward and
backward pass of two MLP critics (loss = sum of both outputs) three ways: each critic on its own
(``nn.Sequential`` of ``nn.Linear``), the two stacked per layer into ``torch.baddbmm`` products, and
``torch.func.vmap`` of ``functional_call`` over their stacked parameters. Every form reads the same
parameters, so gradients reach each critic's own tensors. It prints the best time of ``--repeats``
rounds in microseconds.
"""

from __future__ import annotations

import argparse
import copy
import time
from collections.abc import Callable
from functools import partial

import torch
from torch import nn
from torch.func import functional_call, vmap

CASES = [(4, (64, 64), 2, 64), (2, (256, 256), 3, 128), (8, (64, 64), 4, 64)]
"""(observation size, hidden layers, actions, batch) of CartPole, MountainCar and LunarLander."""


def critic(obs_dim: int, hidden: tuple[int, int], n_actions: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Linear(obs_dim, hidden[0]), nn.ReLU(), nn.Linear(hidden[0], hidden[1]), nn.ReLU(),
        nn.Linear(hidden[1], n_actions),
    )  # fmt: skip


def best_us(step: Callable[[], None], repeats: int, calls: int = 300) -> float:
    """Best microseconds per ``step()`` over ``repeats`` rounds of ``calls``, after a warm-up."""
    for _ in range(20):
        step()
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        for _ in range(calls):
            step()
        best = min(best, (time.perf_counter() - start) / calls)
    return 1e6 * best


def one_by_one(critics: nn.ModuleList, x: torch.Tensor) -> None:
    """Each critic's forward on its own, then one backward pass."""
    sum(network(x).sum() for network in critics).backward()


def stacked_baddbmm(critics: nn.ModuleList, x: torch.Tensor) -> None:
    """Every layer's weights stacked over the critics and applied as one ``baddbmm``."""
    layers = [index for index, layer in enumerate(critics[0]) if isinstance(layer, nn.Linear)]
    y = x.expand(len(critics), *x.shape)
    for place, index in enumerate(layers):
        weight = torch.stack([network[index].weight for network in critics]).transpose(1, 2)
        bias = torch.stack([network[index].bias for network in critics]).unsqueeze(1)
        y = torch.baddbmm(bias, y, weight)
        y = y.relu() if place < len(layers) - 1 else y
    y.sum().backward()


def stacked_vmap(critics: nn.ModuleList, x: torch.Tensor, skeleton: nn.Module) -> None:
    """``vmap`` of ``functional_call`` on ``skeleton`` (a parameter-free copy) over the stacked
    parameters."""
    names = [name for name, _ in critics[0].named_parameters()]
    stacked = {name: torch.stack([network.get_parameter(name) for network in critics]) for name in names}
    vmap(lambda params: functional_call(skeleton, params, (x,)))(stacked).sum().backward()


def main() -> None:
    formatter = argparse.RawDescriptionHelpFormatter
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=formatter)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    print("| obs, hidden, actions, batch | one by one (us) | baddbmm (us) | vmap (us) |")
    print("|---|---|---|---|")
    for obs_dim, hidden, n_actions, batch in CASES:
        critics = nn.ModuleList(critic(obs_dim, hidden, n_actions) for _ in range(2))
        skeleton = copy.deepcopy(critics[0]).to("meta")
        x = torch.randn(batch, obs_dim)
        steps = [
            partial(one_by_one, critics, x),
            partial(stacked_baddbmm, critics, x),
            partial(stacked_vmap, critics, x, skeleton),
        ]
        times = " | ".join(f"{best_us(step, args.repeats):.0f}" for step in steps)
        print(f"| {obs_dim}, {list(hidden)}, {n_actions}, {batch} | {times} |")


if __name__ == "__main__":
    main()
