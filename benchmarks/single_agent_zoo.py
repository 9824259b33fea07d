"""SoftDQN and DiscreteSAC against SB3's DQN and PPO with the RL Zoo's tuned settings, on single-agent envs.

Run: nice -n 10 python benchmarks/single_agent_zoo.py --envs CartPole-v1 --seeds 5 --threads 1
     [--algorithms soft_dqn discrete_sac dqn ppo random] [--results benchmarks/single_agent_zoo.json]
     [--timesteps 200000] [--param target_entropy_ratio=0.25 --variant ratio0.25]

Every algorithm trains each env for the RL Zoo's DQN budget (``n_timesteps`` of rl_zoo3's
``hyperparams/dqn.yml``, read from the installed ``rl-zoo3`` package: ``pip install -e ".[zoo]"``) with
seeds 0..N-1; DQN and PPO with the Zoo's tuned settings for the env (``dqn.yml``, ``ppo.yml``: PPO's
``n_envs`` copies, ``lin_`` schedules and ``normalize``, the evaluation then reading the training
copies' observation statistics), SoftDQN and DiscreteSAC with those of
``sb3_hgrn/hyperparams/<algorithm>.yml``. The score of a run is the mean return of its greedy policy
over ``--eval-episodes`` episodes of an env seeded ``seed + 1000``. The table gives the IQM over seeds
with its 95 % stratified-bootstrap interval (:mod:`sb3_hgrn.experiments.stats`, rliable) and the wall
time per 100k env steps (training only), with its ratio to DQN's. ``random`` is the floor: uniformly
random actions, evaluated the same way.

``--timesteps N`` trains every algorithm for N env steps instead (MinAtar's 5M frames are hours per run
on a CPU); the schedules keep their fractions of the budget, except the MinAtar paper's DQN
exploration, which keeps its 100k frames. Such runs are kept under ``env@N/algorithm/seed``, apart from
the full budget's.

``--param KEY=VALUE ...`` overrides settings of SoftDQN and DiscreteSAC (as the CLI's ``--param``; dotted
keys reach into ``policy_kwargs``); such runs need a ``--variant NAME`` and are kept under
``env/algorithm:NAME/seed``, apart from those of the packaged settings.

Runs go one at a time, seed-major (every algorithm's seed 0 first), and each finished run is added
to the ``--results`` JSON file at once (written to a temporary file, then renamed), so a killed
benchmark resumes where it stopped and a partial one still prints the seeds it finished.
Envs: CartPole-v1, Acrobot-v1, MountainCar-v0, LunarLander-v3 (needs ``gymnasium[box2d]``),
MinAtar/Breakout-v1 and MinAtar/SpaceInvaders-v1 (need ``minatar``; the RL Zoo has no MinAtar
settings, so DQN runs there with those of the MinAtar paper, :data:`MINATAR_DQN`).
"""

from __future__ import annotations

import argparse
import ast
import importlib.util
import json
import time
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch as th
import yaml
from stable_baselines3 import DQN, PPO
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.vec_env import VecEnv, VecNormalize

from sb3_hgrn.common.files import write_text_atomically
from sb3_hgrn.common.torch_layers import AgentViewCNN
from sb3_hgrn.envs.registration import ensure_registered
from sb3_hgrn.experiments.config import parse_assignments
from sb3_hgrn.experiments.single_agent import SINGLE_AGENT_PRESETS, env_settings, make_model
from sb3_hgrn.experiments.stats import iqm_interval

ZOO_ONLY_KEYS = {"n_timesteps", "policy", "n_envs", "normalize"}
"""Keys of a Zoo entry that are not arguments of the algorithm."""

ZOO_ALGORITHMS = {"dqn": DQN, "ppo": PPO}
"""The SB3 anchors, by the name of their RL Zoo hyperparameter file."""

RANDOM = "random"
"""The floor: uniformly random actions, evaluated as the trained runs are (no training)."""


class RandomActions:
    """Uniformly random actions, called as ``evaluate_policy`` calls a model.

    :param n_actions: the size of the env's ``Discrete`` action space.
    :param seed: seed of its own random generator.
    """

    def __init__(self, n_actions: int, seed: int):
        self.n_actions = n_actions
        self.rng = np.random.default_rng(seed)

    def predict(self, observation: np.ndarray, state=None, episode_start=None, deterministic=False):
        """One random action per env copy ``(n_envs,)`` of a batched ``observation``."""
        return self.rng.integers(self.n_actions, size=len(observation)), state


MINATAR_DQN: dict[str, Any] = dict(
    n_timesteps=5_000_000,
    policy="CnnPolicy",
    learning_rate=2.5e-4,
    batch_size=32,
    buffer_size=100_000,
    learning_starts=5000,
    gamma=0.99,
    target_update_interval=1000,
    train_freq=1,
    gradient_steps=1,
    exploration_initial_eps=1.0,
    exploration_final_eps=0.1,
    exploration_fraction=0.02,  # 100k of 5M frames (MINATAR_EXPLORATION_STEPS)
    policy_kwargs=dict(
        features_extractor_class=AgentViewCNN,
        features_extractor_kwargs=dict(features_dim=128, channels=[16]),
        net_arch=[],
        optimizer_class=th.optim.RMSprop,
        optimizer_kwargs=dict(alpha=0.95, centered=True, eps=0.01),
    ),
)
MINATAR_EXPLORATION_STEPS = 100_000
"""The RL Zoo has no MinAtar settings: DQN as in the MinAtar paper (Young and Tian, 2019, Table 2 and
its examples/dqn.py: one 3x3 convolution of 16 channels, 128 hidden units, centred RMSProp)."""


def zoo_settings(algorithm: str, env: str, timesteps: int | None = None) -> dict[str, Any]:
    """The RL Zoo's settings of ``algorithm`` (``"dqn"``, ``"ppo"``) for ``env`` from the installed
    rl_zoo3's ``hyperparams/<algorithm>.yml`` (``policy_kwargs``, a ``dict(...)`` string there, read as
    literals), or for DQN on MinAtar :data:`MINATAR_DQN` (its exploration lasting
    :data:`MINATAR_EXPLORATION_STEPS` of ``timesteps``, the paper's budget by default); ``SystemExit``
    naming the install command or the env when they are missing."""
    if algorithm == "dqn" and env.startswith("MinAtar/"):
        budget = timesteps or MINATAR_DQN["n_timesteps"]
        return {**MINATAR_DQN, "exploration_fraction": min(1.0, MINATAR_EXPLORATION_STEPS / budget)}
    spec = importlib.util.find_spec("rl_zoo3")
    if spec is None or not spec.submodule_search_locations:
        raise SystemExit(
            "The RL Zoo's hyperparameters need the rl-zoo3 package: "
            'pip install -e ".[zoo]" (or pip install rl-zoo3)'
        )
    path = Path(spec.submodule_search_locations[0]) / "hyperparams" / f"{algorithm}.yml"
    table = yaml.safe_load(path.read_text(encoding="utf-8"))
    if env not in table:
        raise SystemExit(f"{path} has no {algorithm.upper()} settings for {env!r}.")
    settings = dict(table[env])
    if isinstance(settings.get("policy_kwargs"), str):
        settings["policy_kwargs"] = literal_call_kwargs(settings["policy_kwargs"])
    return settings


def zoo_value(value: Any) -> Any:
    """A Zoo setting as SB3 takes it: ``"lin_X"`` becomes the schedule falling linearly from ``X``
    to 0 over training (rl_zoo3's ``linear_schedule``); other values are kept."""
    if isinstance(value, str) and value.startswith("lin_"):
        initial = float(value[len("lin_") :])
        return lambda progress_remaining: progress_remaining * initial
    return value


def make_zoo_model(algorithm: str, env: str, seed: int) -> tuple[BaseAlgorithm, VecEnv]:
    """An SB3 anchor with the Zoo's settings for ``env`` and its greedy evaluation env: one copy seeded
    ``seed + 1000``, normalised with the training copies' statistics where the Zoo normalises."""
    settings = zoo_settings(algorithm, env)
    arguments = {key: zoo_value(value) for key, value in settings.items() if key not in ZOO_ONLY_KEYS}
    train_env = make_vec_env(ensure_registered(env), n_envs=int(settings.get("n_envs", 1)), seed=seed)
    eval_env = make_vec_env(env, n_envs=1, seed=seed + 1000)
    if settings.get("normalize"):
        train_env = VecNormalize(train_env, gamma=arguments.get("gamma", 0.99))
        eval_env = VecNormalize(eval_env, training=False, norm_reward=False)
        eval_env.obs_rms = train_env.obs_rms  # the same statistics object: read after training
    model = ZOO_ALGORITHMS[algorithm](settings["policy"], train_env, seed=seed, **arguments)
    return model, eval_env


def literal_call_kwargs(text: str) -> dict[str, Any]:
    """The keyword arguments of a ``dict(key=literal, ...)`` string, without evaluating code."""
    call = ast.parse(text, mode="eval").body
    if not isinstance(call, ast.Call) or not isinstance(call.func, ast.Name) or call.func.id != "dict":
        raise SystemExit(f"Expected policy_kwargs of the form dict(key=value, ...), got {text!r}.")
    return {keyword.arg: ast.literal_eval(keyword.value) for keyword in call.keywords}


def train_once(
    algorithm: str, env: str, seed: int, timesteps: int, eval_episodes: int, params: dict[str, Any]
) -> dict[str, Any]:
    """Train one run (SoftDQN and DiscreteSAC with ``params`` over their settings) and evaluate its
    greedy policy: its score, steps and training wall time (``random``: no training, the uniform
    policy evaluated, 0 steps and seconds)."""
    eval_env = None  # a Monitor env reset with seed + 1000, unless the model needs its own (PPO's)
    if algorithm == RANDOM:
        eval_env = Monitor(gym.make(ensure_registered(env)))
        eval_env.reset(seed=seed + 1000)
        policy = RandomActions(int(eval_env.action_space.n), seed)
        score, _ = evaluate_policy(policy, eval_env, n_eval_episodes=eval_episodes)
        return {"score": float(score), "env_steps": 0, "wall_time_s": 0.0}
    if algorithm == "dqn":
        settings = zoo_settings("dqn", env, timesteps)
        arguments = {key: value for key, value in settings.items() if key not in ZOO_ONLY_KEYS}
        model = DQN(settings["policy"], Monitor(gym.make(ensure_registered(env))), seed=seed, **arguments)
    elif algorithm in ZOO_ALGORITHMS:
        model, eval_env = make_zoo_model(algorithm, env, seed)
    else:
        model = make_model(algorithm, env, env_settings(algorithm, env, params), seed)
    start = time.perf_counter()
    model.learn(timesteps)
    wall_time = time.perf_counter() - start
    if eval_env is None:
        eval_env = Monitor(gym.make(env))
        eval_env.reset(seed=seed + 1000)
    score, _ = evaluate_policy(model, eval_env, n_eval_episodes=eval_episodes, deterministic=True)
    return {"score": float(score), "env_steps": int(model.num_timesteps), "wall_time_s": wall_time}


def load_results(path: Path) -> dict[str, dict[str, Any]]:
    """Finished runs by ``env/algorithm/seed``, from an earlier (partial) benchmark."""
    return json.loads(path.read_text(encoding="utf-8")) if path.exists() else {}


def table_rows(results: dict[str, dict[str, Any]], envs: list[str], algorithms: list[str]) -> list[str]:
    """Markdown rows: env, algorithm (``name:variant`` for a variant's runs), seeds, IQM [95 % CI],
    wall s per 100k env steps, ratio to DQN."""
    rows = []
    for env in envs:
        per_algorithm = {
            algorithm: [run for key, run in results.items() if key.startswith(f"{env}/{algorithm}/")]
            for algorithm in algorithms
        }
        dqn_runs = per_algorithm.get("dqn") or []
        dqn_time = (
            np.mean([run["wall_time_s"] / run["env_steps"] * 1e5 for run in dqn_runs]) if dqn_runs else None
        )
        for algorithm, runs in per_algorithm.items():
            if not runs:
                continue
            scores = np.array([[run["score"]] for run in runs])
            interval = iqm_interval(scores)
            times, ratio = "-", "-"  # none for the untrained floor
            if algorithm != RANDOM:
                per_100k = float(np.mean([run["wall_time_s"] / run["env_steps"] * 1e5 for run in runs]))
                times, ratio = f"{per_100k:.0f}", f"{per_100k / dqn_time:.2f}" if dqn_time else "-"
            rows.append(
                f"| {env} | {algorithm} | {len(runs)} | {interval.estimate:.1f} "
                f"[{interval.low:.1f}, {interval.high:.1f}] | {times} | {ratio} |"
            )
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--envs", nargs="+", default=["CartPole-v1"])
    parser.add_argument("--algorithms", nargs="+", default=[*SINGLE_AGENT_PRESETS, *ZOO_ALGORITHMS, RANDOM],
                        choices=[*SINGLE_AGENT_PRESETS, *ZOO_ALGORITHMS, RANDOM])  # fmt: skip
    parser.add_argument("--seeds", type=int, default=5, help="seeds 0..N-1")
    parser.add_argument("--eval-episodes", type=int, default=20)
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    parser.add_argument("--results", default="benchmarks/single_agent_zoo.json", help="JSON of finished runs")
    parser.add_argument(
        "--timesteps", type=int, help="env steps of every run (default: the Zoo DQN's budget)"
    )
    parser.add_argument("--param", nargs="*", default=[], metavar="KEY=VALUE",
                        help="settings of SoftDQN and DiscreteSAC over the packaged ones")  # fmt: skip
    parser.add_argument("--variant", help="name of the --param runs, kept as env/algorithm:NAME/seed")
    args = parser.parse_args()
    params = parse_assignments(args.param)
    if bool(params) != bool(args.variant):
        parser.error("--param and --variant go together: name the runs whose settings differ")
    if params and set(args.algorithms) - set(SINGLE_AGENT_PRESETS):
        parser.error(f"--param changes only {', '.join(SINGLE_AGENT_PRESETS)}; drop the others")
    th.set_num_threads(args.threads)
    path = Path(args.results)
    results = load_results(path)
    if args.timesteps is not None and args.timesteps <= 0:
        parser.error(f"--timesteps must be positive, got {args.timesteps}")
    labels = [env if args.timesteps is None else f"{env}@{args.timesteps}" for env in args.envs]
    for env, label in zip(args.envs, labels, strict=True):
        timesteps = args.timesteps or int(zoo_settings("dqn", env)["n_timesteps"])
        for seed in range(args.seeds):
            for algorithm in args.algorithms:
                name = f"{algorithm}:{args.variant}" if args.variant else algorithm
                key = f"{label}/{name}/{seed}"
                if key in results:
                    continue
                results[key] = train_once(algorithm, env, seed, timesteps, args.eval_episodes, params)
                write_text_atomically(path, json.dumps(results, indent=1))
                print(f"{key}: {results[key]}", flush=True)
    print(f"\n{args.threads} torch thread(s), greedy return over {args.eval_episodes} episodes")
    print("| env | algorithm | seeds | IQM [95 % CI] | wall s / 100k steps | x DQN |")
    print("| --- | --- | --- | --- | --- | --- |")
    variants = [f"{algorithm}:{args.variant}" for algorithm in args.algorithms] if args.variant else []
    names = list(dict.fromkeys([*args.algorithms, "dqn", RANDOM, *variants]))  # beside the packaged runs
    print("\n".join(table_rows(results, labels, names)))


if __name__ == "__main__":
    main()
