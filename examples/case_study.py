"""Case study (the paper's interpretability figure): agent 0 walks past agents 1 and 2.

Run: python examples/case_study.py [--model PATH] [--timesteps 200000] [--out case_study.png]
(the default run took 48 s on a 2-core CPU, 1 thread, beside two other training jobs).

Without ``--model`` it first trains a small Soft-HGRN on random Surviving maps of the case study's size
(24 x 24, 50 agents, about the density of the paper's 100 agents on 32 x 32; 4 resource points,
100-step episodes, ``--timesteps`` agent-steps). ``--model`` loads a SoftHGRN saved by
``examples/train_surviving.py`` instead; it must have been trained on a map of 17 to 32 cells (the same
observation width, e.g. the paper's 32 x 32).

The hand-made map (24 x 24, no resource points, so no food regrows):

- agent 0 starts at cell (11, 1) and walks along row 11 to (11, 22), one cell per step;
- agent 1 stands at (8, 7) and agent 2 at (14, 16), each eating in the middle of a 3 x 3 patch of food.

Agents 1 and 2 are 3 rows from the corridor: within agent 0's communication range (Chebyshev distance
3) while it passes them (agent 1 for columns 4-10, agent 2 for columns 13-19), but their food lies
outside agent 0's own 3 x 3 view, so agent 0 can learn of it only through the messages it attends to.
Its food store (10 at the start) runs out after 10 steps, so it passes agent 2 hungry.

Every action is scripted (agent 0 moves right, all others eat in place), so the scene is the same for
every model and the figure shows how the network reads it: the recurrent state is the network's own,
threaded through the episode. The figure plots, per step, agent 0's attention over itself and agents 1
and 2 in both attention layers (heads averaged), the mean reset gate of its GRU (and of all agents),
and the policy's probabilities ``softmax(Q / alpha)`` of moving up (towards agent 1's food) or down
(towards agent 2's food) against those of its other actions.
"""

from __future__ import annotations

import argparse
import io
import textwrap
import time

import numpy as np
import torch as th
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Patch, Rectangle

from sb3_hgrn import GraphVecEnv, SoftHGRN, make_graph_vec_env
from sb3_hgrn.analysis import EpisodeRecord, attention_by_agent, record_episode
from sb3_hgrn.envs.surviving_v0 import EAT

MAP_SIZE = 24
CORRIDOR_ROW = 11
AGENT_CELLS = np.array([[CORRIDOR_ROW, 1], [8, 7], [14, 16]])
N_STEPS = MAP_SIZE - 2  # agent 0 reaches the last interior column at the last step
MOVE_RIGHT, MOVE_UP, MOVE_DOWN = 3, 0, 1  # actions: 0 x - 1 (up), 1 x + 1 (down), 3 y + 1 (right)
TRAIN_KWARGS = {"n_agents": 50, "map_size": MAP_SIZE, "n_resources": 4, "max_cycles": 100}


def case_env_kwargs() -> dict:
    """Surviving arguments of the hand-made map."""
    food = np.zeros((MAP_SIZE, MAP_SIZE), dtype=np.int64)
    for x, y in AGENT_CELLS[1:3]:
        food[x - 1 : x + 2, y - 1 : y + 2] = 5
    return {
        "n_agents": len(AGENT_CELLS),
        "map_size": MAP_SIZE,
        "n_resources": 0,
        "max_cycles": N_STEPS + 1,
        "agent_positions": AGENT_CELLS,
        "food_map": food[1:-1, 1:-1],
    }


def scripted_actions() -> np.ndarray:
    """``(N_STEPS, n_agents)``: agent 0 moves right, the others eat where they stand."""
    actions = np.full((N_STEPS, len(AGENT_CELLS)), EAT)
    actions[:, 0] = MOVE_RIGHT
    return actions


def load_or_train(path: str | None, timesteps: int, seed: int, env: GraphVecEnv) -> SoftHGRN:
    """The SoftHGRN at ``path``, or one trained on random maps of the case study's size, on ``env``."""
    if path is None:
        train_env = make_graph_vec_env("surviving_v0", n_envs=2, seed=seed, env_kwargs=TRAIN_KWARGS)
        model = SoftHGRN("GraphPolicy", train_env, seed=seed)
        start = time.perf_counter()
        model.learn(timesteps)
        print(f"trained {timesteps} agent-steps on {TRAIN_KWARGS}, {time.perf_counter() - start:.0f} s")
        path = io.BytesIO()
        model.save(path)
        path.seek(0)
    return SoftHGRN.load(path, env=env)  # moves the model onto the case study's agent count


def in_range_spans(axis: Axes, record: EpisodeRecord) -> None:
    """Shade the steps at which agents 1 and 2 are in agent 0's neighbour list."""
    for other, color in ((1, "tab:orange"), (2, "tab:green")):
        listed = (record.neighbors == other).any(axis=1)
        for step in np.flatnonzero(listed):
            axis.axvspan(step - 0.5, step + 0.5, color=color, alpha=0.08, lw=0)


def plot(record: EpisodeRecord, model: SoftHGRN, food: np.ndarray, source: str, out: str) -> None:
    """Draw the map and agent 0's attention, reset gate and move probabilities per step into ``out``.

    :param record: the recorded episode (``N_STEPS`` steps).
    :param model: the recorded model (for its temperature).
    :param food: ``(MAP_SIZE, MAP_SIZE)`` food before the episode, ``-1`` on walls.
    :param source: where the model comes from, printed on the figure.
    :param out: PNG path.
    """
    steps = np.arange(N_STEPS)
    figure = Figure(figsize=(13, 9.5))
    FigureCanvasAgg(figure)
    grid = figure.add_gridspec(4, 2, width_ratios=[1, 1.6], hspace=0.35, wspace=0.15)

    map_axis = figure.add_subplot(grid[:2, 0])
    map_axis.imshow(np.where(food < 0, np.nan, food), cmap="Greens", vmin=0, vmax=6)
    path = record.cells[:, 0]
    map_axis.plot(path[:, 1], path[:, 0], "-", color="tab:blue", lw=2)
    for agent, color in ((0, "tab:blue"), (1, "tab:orange"), (2, "tab:green")):
        x, y = record.cells[0, agent]
        map_axis.plot(y, x, "o", color=color, ms=9, mec="black")
        map_axis.annotate(str(agent), (y, x), xytext=(5, 5), textcoords="offset points", fontsize=10)
    for agent, color in ((1, "tab:orange"), (2, "tab:green")):
        x, y = record.cells[0, agent]
        map_axis.add_patch(Rectangle((y - 3.5, x - 3.5), 7, 7, fill=False, ls="--", color=color))
    map_axis.annotate("", xy=(path[-1, 1], path[-1, 0]), xytext=(path[-3, 1], path[-3, 0]),
                      arrowprops={"arrowstyle": "->", "color": "tab:blue", "lw": 2})  # fmt: skip
    map_axis.set_title("hand-made map: food (green), agent 0's walk,\nranges of agents 1 and 2 (dashed)")
    map_axis.set_xticks([])
    map_axis.set_yticks([])

    n_agents = record.actions.shape[1]
    series_axes = []
    for row, (weights, title) in enumerate(
        ((record.attention1, "attention layer 1"), (record.attention2, "attention layer 2"))
    ):
        axis = figure.add_subplot(grid[row, 1], sharex=series_axes[0] if series_axes else None)
        by_agent = attention_by_agent(weights, record.neighbors, agent=0, n_agents=n_agents)
        for agent, color in ((0, "tab:blue"), (1, "tab:orange"), (2, "tab:green")):
            axis.plot(steps, by_agent[:, agent], "o-", ms=3, color=color)
        axis.set_ylim(-0.03, 1.03)
        axis.set_ylabel("weight")
        axis.set_title(f"agent 0's {title}: weight on itself, agent 1, agent 2 (mean of heads)", fontsize=10)
        series_axes.append(axis)

    gate_axis = figure.add_subplot(grid[2, 1], sharex=series_axes[0])
    gate_axis.plot(steps, record.reset_gate, "o-", ms=3, color="tab:blue")
    gate_axis.plot(steps, record.reset_gate_all, "--", color="black")
    gate_axis.set_ylabel("mean reset gate")
    gate_axis.set_title("GRU reset gate of agent 0 (and of all agents), mean over hidden units", fontsize=10)
    series_axes.append(gate_axis)

    policy_axis = figure.add_subplot(grid[3, 1], sharex=series_axes[0])
    alpha = float(model.policy.temperature.alpha.detach()[0])
    probabilities = th.softmax(th.as_tensor(record.outputs[:, 0]) / alpha, dim=-1).numpy()
    policy_axis.plot(steps, probabilities[:, MOVE_UP], "o-", ms=3, color="tab:orange")
    policy_axis.plot(steps, probabilities[:, MOVE_DOWN], "o-", ms=3, color="tab:green")
    policy_axis.plot(steps, probabilities[:, [2, 3, 4]].sum(1), "-.", color="grey")
    policy_axis.set_ylim(-0.03, 1.03)
    policy_axis.set_ylabel("probability")
    policy_axis.set_xlabel("step (agent 0 at column step + 1)")
    policy_axis.set_title(f"agent 0's policy softmax(Q / alpha), alpha = {alpha:.3f}", fontsize=10)
    series_axes.append(policy_axis)

    for axis in series_axes:
        in_range_spans(axis, record)
        axis.axvline(9.5, color="grey", ls=":", lw=1)  # agent 0's store is empty from step 10 on
        axis.grid(alpha=0.3)
    series_axes[-1].set_xticks(steps[::2])

    key_axis = figure.add_subplot(grid[2:, 0])
    key_axis.axis("off")
    handles = [
        Line2D([], [], color="tab:blue", marker="o", ms=3, label="agent 0 (attention: itself)"),
        Line2D([], [], color="tab:orange", marker="o", ms=3, label="agent 1 (policy: moving up, towards it)"),
        Line2D(
            [], [], color="tab:green", marker="o", ms=3, label="agent 2 (policy: moving down, towards it)"
        ),
        Line2D([], [], color="black", ls="--", label=f"reset gate: mean of all {n_agents} agents"),
        Line2D([], [], color="grey", ls="-.", label="policy: left, right or eat"),
        Patch(color="tab:orange", alpha=0.2, label="agent 1 in agent 0's range"),
        Patch(color="tab:green", alpha=0.2, label="agent 2 in agent 0's range"),
        Line2D([], [], color="grey", ls=":", lw=1, label="agent 0's food store is empty from here"),
    ]
    key_axis.legend(handles=handles, loc="upper left", fontsize=9, frameon=False)
    note = textwrap.fill(f"model: {source}", 50) + "\nactions scripted: agent 0 moves right, the others eat"
    key_axis.text(0.0, 0.0, note, fontsize=9, va="bottom")
    figure.suptitle("Soft-HGRN case study: agent 0 walks past agents 1 and 2")
    figure.savefig(out, dpi=110, bbox_inches="tight")


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--model", help="SoftHGRN .zip to load instead of training one")
    parser.add_argument("--timesteps", type=int, default=200_000, help="agent-steps of training")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=th.get_num_threads())
    parser.add_argument("--out", default="case_study.png")
    args = parser.parse_args()
    th.set_num_threads(args.threads)
    start = time.perf_counter()
    env = make_graph_vec_env("surviving_v0", env_kwargs=case_env_kwargs())
    model = load_or_train(args.model, args.timesteps, args.seed, env)
    env.reset()
    food = env.envs[0].food_grid()  # the map before the episode (agents 1 and 2 eat during it)
    record = record_episode(model, env, N_STEPS, agent=0, scripted_actions=scripted_actions())
    source = args.model or (
        f"Soft-HGRN trained by this script, {args.timesteps:,} agent-steps on random {MAP_SIZE} x {MAP_SIZE} "
        f"maps of {TRAIN_KWARGS['n_agents']} agents, seed {args.seed}"
    )
    plot(record, model, food, source, args.out)
    print(f"saved {args.out} ({time.perf_counter() - start:.0f} s in all)")


if __name__ == "__main__":
    main()
