"""Throughput and memory of Soft-HGRN on Surviving: env, collection, updates, replay storage.

Run: python benchmarks/throughput.py [--agents 100] [--sizes default paper paper-bf16] [--buffer-rows 50000]
     [--device cpu|cuda|auto]

Prints, for Surviving with ``--agents`` agents:
- env steps/s with random actions (array API with the graph, the graph VecEnv, the PettingZoo dict API);
- collection steps/s with the policy (1 and 4 env copies, no training);
- per network size: gradient updates/s of ``SoftHGRN.train`` and the bare network time of the same
  batch (target forward + forward + backward + optimiser step); their ratio is the learner overhead;
  and the floor set by the dense matrix products alone (:func:`dense_update_flops` at the rate of a
  float32 matrix product of the layers' width measured here), which no float32 update goes below;
- bytes per replay row and the resident memory of a filled ``--buffer-rows`` buffer (measured first:
  once learning has started, freed memory stays with the process, ``sb3_hgrn.common.memory``), and
  peak RSS. ``SB3_HGRN_KEEP_FREED_MEMORY=0 python benchmarks/throughput.py`` runs without that.

With 100 agents each figure the original code was measured at on a 2-core CPU (:data:`ORIGINAL`) is
set beside it as a speed-up: the env alone, collecting with 1 copy, and the paper-size update of 128
graphs.
"""

from __future__ import annotations

import argparse
import resource
import time

import numpy as np
import torch as th
import torch.nn.functional as F

from sb3_hgrn import SoftHGRN, make_graph_vec_env
from sb3_hgrn.common.buffers import GraphReplayBuffer
from sb3_hgrn.common.hgrn import PAPER_SIZE
from sb3_hgrn.envs import surviving_v0

ORIGINAL = {"env steps/s": 2200.0, "collect env steps/s": 99.0, "paper update s, 128 graphs": 4.2}
"""The original code's figures, Surviving with 100 agents on a 2-core CPU: env steps/s with random
actions, env steps/s while collecting (one forward per step) and seconds per paper-size update of
128 graphs x 100 agents."""


def speedup(ratio: float, n_agents: int, what: str) -> str:
    """`` (N.Nx the original's FIGURE)`` for a measured ``ratio`` to the original's figure ``what``
    (:data:`ORIGINAL`), or nothing when the run is not at the original's 100 agents."""
    return "" if n_agents != 100 else f"  ({ratio:.2f}x the original's {ORIGINAL[what]:g} {what})"


SIZES = {
    "default": {},
    "paper": PAPER_SIZE,
    "paper-bf16": {**PAPER_SIZE, "mixed_precision": True},  # bfloat16 matrix products (HGRN docs)
}


def best_rate(run, count: int, repeats: int = 3) -> float:
    """Highest ``count / seconds`` over ``repeats`` calls of ``run()`` (CUDA work finished in the time)."""
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        run()
        if th.cuda.is_available():
            th.cuda.synchronize()
        best = min(best, time.perf_counter() - start)
    return count / best


def dense_update_flops(network: th.nn.Module, rows: int) -> float:
    """Floating-point operations of the dense matrix products of one update of ``rows`` agent rows:
    every weight matrix (linear layers, GRU) multiplies each row once in the target network's forward,
    once in the online forward and twice in its backward (input and weight gradients), 2 operations
    per multiply-add. The sparse attention, element-wise work and the optimiser are left out."""
    weights = sum(parameter.numel() for parameter in network.parameters() if parameter.dim() == 2)
    return 2.0 * 4 * weights * rows


def matmul_flops_per_s(rows: int, width: int, device: str, repeats: int = 5) -> float:
    """This machine's rate of float32 matrix products ``(rows, width) @ (width, 4 * width)`` at the
    current torch thread count: the pace the dense layers of an update can go at best."""
    left = th.randn(rows, width, device=device)
    right = th.randn(width, 4 * width, device=device)
    left @ right  # warm-up
    return best_rate(lambda: left @ right, 2 * rows * width * 4 * width, repeats)


def resident_bytes() -> int:
    with open("/proc/self/statm") as statm:
        return int(statm.read().split()[1]) * resource.getpagesize()


def env_rates(n_agents: int, steps: int) -> None:
    env = surviving_v0.parallel_env(n_agents=n_agents, max_cycles=10**9)
    env.reset_arrays(seed=0)
    actions = np.random.default_rng(0).integers(0, 5, size=(steps, n_agents))

    def array_api():
        for step_actions in actions:
            env.step_arrays(step_actions)
            env.neighbors()

    vec_env = make_graph_vec_env("surviving_v0", seed=0, env_kwargs={"n_agents": n_agents})
    vec_env.reset()

    def graph_vec_env():
        for step_actions in actions:
            vec_env.step(step_actions)

    env.reset(seed=0)
    dict_actions = [dict(zip(env.agents, row.tolist(), strict=True)) for row in actions]

    def dict_api():
        for step_actions in dict_actions:
            env.step(step_actions)

    for name, run in (
        ("array API + graph", array_api),
        ("graph VecEnv", graph_vec_env),
        ("dict API", dict_api),
    ):
        rate = best_rate(run, steps)
        versus = speedup(rate / ORIGINAL["env steps/s"], n_agents, "env steps/s")
        print(f"env  {name:18s} {rate:9.0f} env steps/s  {rate * n_agents:11.0f} agent-steps/s{versus}")


def collection_rates(n_agents: int, steps: int, device: str) -> None:
    for n_copies in (1, 4):
        env = make_graph_vec_env("surviving_v0", n_envs=n_copies, seed=0, env_kwargs={"n_agents": n_agents})
        # no training: collection only
        model = SoftHGRN("GraphPolicy", env, learning_starts=10**9, seed=0, device=device)
        total = steps * env.num_envs
        model.learn(env.num_envs * 10)  # warm-up
        rate = best_rate(lambda model=model, total=total: model.learn(total), steps, repeats=2)
        env_steps = rate * n_copies
        versus = speedup(env_steps / ORIGINAL["collect env steps/s"], n_agents, "collect env steps/s")
        print(
            f"collect {n_copies} x {n_agents} agents: {rate:7.0f} vec-steps/s {env_steps:7.0f} env steps/s "
            f"{rate * env.num_envs:9.0f} agent-steps/s (policy forward, env step, replay add){versus}"
        )


def update_rates(n_agents: int, size: str, batch_size: int, updates: int, device: str) -> None:
    env = make_graph_vec_env("surviving_v0", n_envs=1, seed=0, env_kwargs={"n_agents": n_agents})
    model = SoftHGRN("GraphPolicy", env, learning_starts=10**9, batch_size=batch_size,
                     policy_kwargs=dict(SIZES[size]), seed=0, device=device)  # fmt: skip
    model.learn(n_agents * 300)  # fill the buffer with 300 steps of collection
    model.train(gradient_steps=1, batch_size=batch_size)  # warm-up
    update_rate = best_rate(
        lambda: model.train(gradient_steps=updates, batch_size=batch_size), updates, repeats=2
    )

    q_net, q_net_target, optimizer = model.policy.q_net, model.policy.q_net_target, model.policy.optimizer
    batch = model.replay_buffer.sample(batch_size)

    def bare_step():
        for _ in range(updates):
            with th.no_grad():
                next_q, _ = q_net_target(batch.next_observations, batch.next_neighbors, batch.next_hidden)
            q_values, _ = q_net(batch.observations, batch.neighbors, batch.hidden)
            loss = F.mse_loss(
                q_values.gather(-1, batch.actions.unsqueeze(-1)).squeeze(-1), next_q.max(-1).values
            )
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()

    bare_rate = best_rate(bare_step, updates, repeats=2)
    flops = dense_update_flops(q_net, batch_size * n_agents)
    hidden_dim = (SIZES[size] or {}).get("hidden_dim", 64)
    floor = flops / matmul_flops_per_s(batch_size * n_agents, hidden_dim, model.device.type)
    n_params = sum(p.numel() for p in q_net.parameters())
    paper_update = "paper update s, 128 graphs"
    versus = ""
    if size.startswith("paper") and batch_size == 128:
        versus = speedup(ORIGINAL[paper_update] * update_rate, n_agents, paper_update)
    print(
        f"update [{size}, {n_params / 1e6:.2f} M params] batch {batch_size} graphs x {n_agents} agents: "
        f"{1 / update_rate:6.3f} s/update ({update_rate:5.2f} updates/s), "
        f"bare network {1 / bare_rate:6.3f} s, "
        f"learner overhead {bare_rate / update_rate:4.2f}x{versus}; dense products alone "
        f"{floor:6.3f} s ({flops / 1e9:.0f} GFLOP at this machine's matmul rate)"
    )


def buffer_memory(n_agents: int, size: str, rows: int) -> None:
    env = make_graph_vec_env("surviving_v0", seed=0, env_kwargs={"n_agents": n_agents})
    state_dim = (SIZES[size] or {"hidden_dim": 64}).get("hidden_dim", 64)
    before = resident_bytes()
    buffer = GraphReplayBuffer(rows * env.num_envs, env.observation_space, env.action_space, device="cpu",
                               n_envs=env.num_envs, n_agents=n_agents, state_dim=state_dim)  # fmt: skip
    for name in ("observations", "next_observations", "neighbors", "next_neighbors", "actions", "rewards",
                 "terminated", "hidden", "episode_starts"):  # fmt: skip
        getattr(buffer, name).fill(1)  # touch every page
    resident = resident_bytes() - before
    print(
        f"buffer [{size}, hidden {state_dim} float16] {buffer.nbytes / rows:8.0f} B/row "
        f"({buffer.nbytes / rows / n_agents:5.0f} B/agent-transition); {rows} rows: "
        f"{buffer.nbytes / 2**30:5.2f} GiB stored, {resident / 2**30:5.2f} GiB resident"
    )
    del buffer


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--agents", type=int, default=100)
    parser.add_argument("--sizes", nargs="+", default=["default", "paper"], choices=sorted(SIZES))
    parser.add_argument("--batch-sizes", nargs="+", type=int, default=[32, 128])
    parser.add_argument("--env-steps", type=int, default=2000)
    parser.add_argument("--collect-steps", type=int, default=200)
    parser.add_argument("--updates", type=int, default=5)
    parser.add_argument("--buffer-rows", type=int, default=50_000)
    parser.add_argument("--threads", type=int, default=th.get_num_threads())
    parser.add_argument("--device", default="cpu", help="where the network runs: cpu, cuda or auto")
    args = parser.parse_args()
    th.set_num_threads(args.threads)
    print(f"Surviving, {args.agents} agents, torch {th.__version__}, {args.threads} threads, {args.device}")
    for size in args.sizes:  # before any learning: freed memory is kept from then on
        buffer_memory(args.agents, size, args.buffer_rows)
    env_rates(args.agents, args.env_steps)
    collection_rates(args.agents, args.collect_steps, args.device)
    for size in args.sizes:
        for batch_size in args.batch_sizes:
            update_rates(args.agents, size, batch_size, args.updates, args.device)
    print(f"peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20:.2f} GiB")


if __name__ == "__main__":
    main()
