"""The value scale of envs, and whether a saved model's GRU still responds to its input.

Run:
    python benchmarks/value_scale.py returns [--envs surviving_v0 examples.tag_mpe2:make_env ...]
    python benchmarks/value_scale.py gru RUN_FOLDER [RUN_FOLDER ...]

``returns`` plays uniform random actions (one env copy, ``--steps`` vec-steps) and prints the mean
and standard deviation of an agent's reward per step and the root mean square of its
``--gamma``-discounted returns (the statistic of ``reward_scale="auto"``).

``gru`` loads the saved model of each run folder (``sb3-hgrn train``'s ``config.yml`` and
``model.zip``), acts with it for 40 steps on a fresh env copy and prints, for its online Q-network:
the mean update gate ``z`` of the GRU, the share of candidate pre-activations beyond 5 in magnitude
(tanh saturated), the standard deviation of the GRU's output over agents and steps, the mean
magnitude of the GRU's input, and the mean magnitude and spread of the Q-values. A GRU whose output
does not vary gives every agent the same Q-values at every step.
"""

from __future__ import annotations

import argparse
import importlib
from pathlib import Path

import numpy as np
import torch as th
import yaml

from sb3_hgrn import make_graph_vec_env
from sb3_hgrn.common.buffers import GraphReplayBuffer
from sb3_hgrn.presets import PRESETS

DEFAULT_ENVS = (
    "surviving_v0", "pursuit_v0", "uav_mbs_v0",
    "examples.spread_mpe2:make_env", "examples.tag_mpe2:make_env",
)  # fmt: skip


def env_maker(name: str):
    """A registered env name, or ``module:function``."""
    if ":" not in name:
        return name
    module, function = name.split(":")
    return getattr(importlib.import_module(module), function)


def random_returns(name: str, steps: int, gamma: float) -> str:
    """One line: reward and discounted-return statistics of uniform random play on env ``name``."""
    env = make_graph_vec_env(env_maker(name), n_envs=1, seed=0)
    buffer = GraphReplayBuffer(
        (steps + 1) * env.num_envs, env.observation_space, env.action_space, "cpu",
        n_envs=env.num_envs, n_agents=env.n_agents, gamma=gamma,
    )  # fmt: skip
    rng = np.random.default_rng(0)
    obs, starts = env.reset(), np.ones(env.num_envs, dtype=bool)
    no_state = np.zeros((env.num_envs, 0), dtype=np.float32)
    for _ in range(steps):
        mask = obs.get("action_mask")
        counts = env.action_space.n if mask is None else mask.sum(axis=1)
        actions = rng.integers(0, counts, size=env.num_envs)
        alive = env.alive
        next_obs, rewards, dones, _ = env.step(actions)
        buffer.add(obs, next_obs, actions, rewards, env.terminations, no_state, starts, no_state, alive)
        obs, starts = next_obs, dones
    rewards = buffer.rewards[: buffer.pos][buffer.alive[: buffer.pos]]
    return f"| {name} | {rewards.mean():.3f} | {rewards.std():.3f} | {buffer.return_rms(gamma):.2f} |"


def gru_health(run: Path) -> str:
    """One line: the GRU's gates and the Q-values of the saved model of run folder ``run``."""
    config = yaml.safe_load((run / "config.yml").read_text())
    env = make_graph_vec_env(env_maker(config["env"]), n_envs=1, seed=7, env_kwargs=config.get("env_kwargs"))
    model = PRESETS[config["preset"]][0].load(run / "model.zip", env=env)
    network, policy = model.policy.q_net, model.policy
    if network.gru is None:
        return f"| {run} | (no GRU) |"
    gru = network.gru.members[0]
    seen: list[tuple[th.Tensor, th.Tensor, th.Tensor]] = []
    hook = gru.register_forward_hook(lambda _, inputs, output: seen.append((*inputs[:2], output)))
    obs, state, q_values = env.reset(), None, []
    for _ in range(40):
        actions, new_state = model.predict(obs, state=state)
        observations, neighbors, _ = policy.to_graphs({k: th.as_tensor(v) for k, v in obs.items()})
        hidden = th.zeros(env.num_envs, policy.state_dim) if state is None else th.as_tensor(state[0][0])
        with th.no_grad():
            q_values.append(network(observations, neighbors, hidden.view(*observations.shape[:2], -1))[0])
        obs, state = env.step(actions)[0], new_state
    hook.remove()
    x, h, out = (th.cat([item[k] for item in seen]).detach() for k in range(3))
    width = gru.hidden_size
    gates_x, gates_h = x @ gru.weight_ih.T + gru.bias_ih, h @ gru.weight_hh.T + gru.bias_hh
    reset = th.sigmoid(gates_x[:, :width] + gates_h[:, :width])
    update = th.sigmoid(gates_x[:, width : 2 * width] + gates_h[:, width : 2 * width])
    candidate = gates_x[:, 2 * width :] + reset * gates_h[:, 2 * width :]
    q = th.cat(q_values)
    return (
        f"| {run} | {update.mean():.3f} | {(candidate.abs() > 5).float().mean():.2f} | "
        f"{out.std(0).mean():.3f} | {x.abs().mean():.2f} | {q.abs().mean():.2f} | {q.std(0).mean():.2f} |"
    )


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    commands = parser.add_subparsers(dest="command", required=True)
    returns = commands.add_parser("returns")
    returns.add_argument("--envs", nargs="+", default=list(DEFAULT_ENVS))
    returns.add_argument("--steps", type=int, default=2000)
    returns.add_argument("--gamma", type=float, default=0.95)
    gru = commands.add_parser("gru")
    gru.add_argument("runs", nargs="+", type=Path)
    args = parser.parse_args()
    th.set_num_threads(1)
    if args.command == "returns":
        print(f"Uniform random actions, {args.steps} vec-steps, gamma {args.gamma}")
        print("| env | reward per step, mean | std | discounted return, RMS |\n|---|---|---|---|")
        for name in args.envs:
            print(random_returns(name, args.steps, args.gamma), flush=True)
    else:
        print("| run | GRU update gate z, mean | candidate saturated | GRU output std | GRU input, mean abs "
              "| Q, mean abs | Q std over agents and steps |\n|---|---|---|---|---|---|---|")  # fmt: skip
        for run in args.runs:
            print(gru_health(run), flush=True)


if __name__ == "__main__":
    main()
