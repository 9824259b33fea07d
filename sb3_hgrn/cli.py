"""``sb3-hgrn`` / ``python -m sb3_hgrn``: train, evaluate and render runs, reproduce the paper's Table 1,
draw its figures and sweep grids of arguments.

Examples::

    sb3-hgrn train --env surviving_v0 --preset soft_hgrn --budget cpu --seed 0
    sb3-hgrn train --env my_package.my_module:make_env --config my_config.yml --preset soft_hgrn
    sb3-hgrn evaluate runs/surviving_v0/soft_hgrn/seed_0 --episodes 10 --epsilon 0.3
    sb3-hgrn render runs/surviving_v0/soft_hgrn/seed_0 --out episode.gif
    sb3-hgrn reproduce table1 --budget cpu --seeds 3 --jobs 2
    sb3-hgrn figure ctc --budget cpu --seeds 3 --jobs 2
    sb3-hgrn sweep --env surviving_v0 --presets soft_hgrn --grid learning_rate=1e-3,3e-4 --seeds 3
    sb3-hgrn tune --env surviving_v0 --preset soft_hgrn --budget cpu --n-trials 50 --n-jobs 2

See docs/cli.md.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from sb3_hgrn.common.files import ModelFileError
from sb3_hgrn.common.vec_env import REGISTERED_ENVS
from sb3_hgrn.experiments.backends import BACKENDS, Backend, make_backend
from sb3_hgrn.experiments.config import BUDGETS, ENV_SPEC_HELP, ConfigError, RunConfig, parse_assignments
from sb3_hgrn.presets import TABLE1


def _positive_int(text: str) -> int:
    try:
        value = int(float(text)) if "e" in text.lower() else int(text.replace("_", ""))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return value


def _add_env_params(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--env-param",
        nargs="+",
        action="extend",
        default=[],
        metavar="KEY=VALUE",
        help="env constructor argument over the config's env_kwargs (e.g. n_agents=20)",
    )


ENV_HELP = (
    f"one of {', '.join(REGISTERED_ENVS)}, or {ENV_SPEC_HELP} (needs --config); with --preset soft_dqn or "
    "discrete_sac, a Gymnasium env id (e.g. CartPole-v1)"
)


def _add_config(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--config",
        nargs="+",
        action="extend",
        metavar="FILE",
        help="YAML config files of one's own over the packaged one, in order, e.g. the best.yml of tune; "
        "a MODULE:ATTR env needs one with its budget (docs/cli.md)",
    )


def _add_trust_config(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--trust-config",
        action="store_true",
        help="trust the run folder: import the env MODULE:ATTR that its config.yml names without --env "
        "naming it too, load models it names for its env (Pursuit controllers) from anywhere, not only "
        "from inside the run folder, and unpickle its model zip in full if it needs it (--trust-pickle); "
        "importing a module or unpickling a file can run code",
    )
    _add_trust_pickle(parser)


def _add_trust_pickle(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--trust-pickle",
        action="store_true",
        help="load a model zip that only full unpickling can load (one saved with a learning-rate "
        "function or a class of one's own, or not by sb3_hgrn's save); unpickling can run code",
    )


def _add_backend(parser: argparse.ArgumentParser) -> None:
    """``--backend`` and the Ray backend's options (sb3_hgrn.experiments.backends)."""
    parser.add_argument(
        "--backend",
        choices=BACKENDS,
        default="local",
        help="local: processes on this machine (default); ray: Ray tasks, on this machine or a cluster",
    )
    parser.add_argument(
        "--address", help="ray: the cluster's address (default: $RAY_ADDRESS, else a new local Ray)"
    )
    parser.add_argument("--cpus-per-run", type=float, help="ray: CPUs reserved per run (default 1)")
    parser.add_argument("--gpus-per-run", type=float, help="ray: GPUs reserved per run (default 0)")


def _backend(args: argparse.Namespace) -> Backend:
    return make_backend(args.backend, args.address, args.cpus_per_run, args.gpus_per_run)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser with its subcommands ``train``, ``evaluate``, ``render``, ``reproduce``,
    ``figure``, ``sweep``, ``tune``."""
    parser = argparse.ArgumentParser(
        prog="sb3-hgrn",
        description="Train, evaluate and render sb3_hgrn runs; reproduce the paper's Table 1 and figures; "
        "sweep grids of arguments (docs/cli.md).",
        epilog="examples:\n" + __doc__.split("Examples::\n\n")[1].split("\n\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    train = commands.add_parser("train", help="train one run into its own folder, then evaluate it")
    train.add_argument("--env", required=True, help=ENV_HELP)
    train.add_argument(
        "--preset",
        required=True,
        help="a name of sb3_hgrn.presets.PRESETS (docs/presets.md), or soft_dqn or discrete_sac for "
        "single-agent Gymnasium envs (docs/single_agent.md)",
    )
    train.add_argument("--budget", default="cpu", help=f"config budget: {', '.join(BUDGETS)} (default cpu)")
    train.add_argument("--seed", type=int, default=0)
    train.add_argument(
        "--timesteps", type=_positive_int, help="agent-steps of training (default: the budget's)"
    )
    train.add_argument(
        "--folder", default="runs", help="root of run folders (<folder>/<env>/<preset>/seed_<seed>)"
    )
    train.add_argument(
        "--param",
        nargs="+",
        action="extend",
        default=[],
        metavar="KEY=VALUE",
        help="algorithm argument over the config (e.g. batch_size=64 policy_kwargs.hidden_dim=32)",
    )
    _add_env_params(train)
    _add_config(train)
    train.add_argument(
        "--save-freq", type=_positive_int, help="save a checkpoint every this many agent-steps"
    )
    train.add_argument(
        "--keep-checkpoints",
        type=int,
        metavar="K",
        help="keep only the newest K checkpoints, replay buffers included (0: all; default: the "
        "budget's keep_checkpoints, else 3)",
    )
    train.add_argument(
        "--save-replay-buffer",
        action="store_true",
        help="keep the replay buffer beside every checkpoint, so a resumed run continues with it",
    )
    train.add_argument(
        "--progress-bar", action="store_true", help="show a progress bar (needs tqdm and rich)"
    )
    train.add_argument("--verbose", type=int, default=1, help="0: quiet, 1: SB3's training logs")
    train.add_argument(
        "--log-interval", type=_positive_int, default=10, help="team episodes between log dumps"
    )
    train.add_argument("--threads", type=_positive_int, help="torch CPU threads")
    train.add_argument("--device", default="auto", help="torch device (default auto)")
    train.add_argument("--overwrite", action="store_true", help="redo a run whose folder holds eval.json")
    train.add_argument(
        "--trust-config",
        action="store_true",
        help="resuming a killed run, unpickle its checkpoint, replay buffer and training state in full "
        "where they need it (unpickling can run code; without it, such files are refused or skipped)",
    )

    evaluate = commands.add_parser("evaluate", help="team return of a saved run")
    evaluate.add_argument("path", help="run folder, its model.zip or a checkpoint")
    evaluate.add_argument("--episodes", type=_positive_int, default=10, help="team episodes (default 10)")
    evaluate.add_argument("--deterministic", action="store_true", help="greedy actions")
    evaluate.add_argument(
        "--epsilon",
        type=float,
        default=0.0,
        help="probability of a uniformly random valid action per agent (the original's evaluation: 0.3)",
    )
    evaluate.add_argument(
        "--actions", action="store_true", help="also print the fraction of agent-steps that took each action"
    )
    evaluate.add_argument(
        "--online",
        action="store_true",
        help="act with the online network (Q-network, actor or acting critic) of a model trained with "
        "policy_kwargs.average_tau",
    )
    evaluate.add_argument(
        "--critic",
        action="store_true",
        help="SAC-HGRN: act with the online first critic's Boltzmann policy softmax(Q / alpha) instead of "
        "the deployed actor (a model trained with behaviour_policy=critic deploys its critic already)",
    )
    evaluate.add_argument("--n-envs", type=_positive_int, help="env copies (default: the run's eval_n_envs)")
    evaluate.add_argument("--seed", type=int, help="env seed (default: the run's seed + 1000)")
    evaluate.add_argument(
        "--env", help="env of a bare .zip outside a run folder, or the MODULE:ATTR env its config.yml names"
    )
    evaluate.add_argument("--threads", type=_positive_int, help="torch CPU threads")
    _add_env_params(evaluate)
    _add_trust_config(evaluate)

    render = commands.add_parser("render", help="write one episode of a saved run as a GIF")
    render.add_argument("path", help="run folder, its model.zip or a checkpoint")
    render.add_argument("--out", default="episode.gif", help="GIF file (default episode.gif)")
    render.add_argument(
        "--steps", type=_positive_int, help="stop after this many steps (default: whole episode)"
    )
    render.add_argument("--fps", type=float, default=10.0, help="frames per second (default 10)")
    render.add_argument("--deterministic", action="store_true", help="greedy actions")
    render.add_argument("--seed", type=int, help="env seed (default: the run's seed + 1000)")
    render.add_argument(
        "--env", help="env of a bare .zip outside a run folder, or the MODULE:ATTR env its config.yml names"
    )
    _add_env_params(render)
    _add_trust_config(render)

    reproduce = commands.add_parser("reproduce", help="reproduce a table of the paper")
    reproduce.add_argument("table", choices=["table1"], help="table1: every Table 1 row on its three envs")
    reproduce.add_argument(
        "--budget", default="cpu", help=f"config budget: {', '.join(BUDGETS)} (default cpu)"
    )
    reproduce.add_argument("--seeds", type=_positive_int, default=3, help="seeds 0..N-1 (default 3)")
    reproduce.add_argument("--folder", default="results", help="results folder (default results)")
    reproduce.add_argument("--jobs", type=_positive_int, default=1, help="training processes at a time")
    reproduce.add_argument(
        "--threads", type=_positive_int, help="torch threads per process (default 1 if jobs > 1)"
    )
    reproduce.add_argument(
        "--save-freq", type=_positive_int, help="checkpoint every this many agent-steps (killed runs resume)"
    )
    reproduce.add_argument(
        "--presets", nargs="+", default=list(TABLE1), help="rows (default: all of Table 1)"
    )
    reproduce.add_argument(
        "--envs",
        nargs="+",
        default=["uav_mbs_v0", "surviving_v0", "pursuit_v0"],
        help="columns (default all three)",
    )
    _add_backend(reproduce)

    figure = commands.add_parser("figure", help="draw a figure of the paper, training its runs first")
    figure.add_argument(
        "name",
        metavar="NAME",
        help="ctc (CTC learning curves), alpha (temperature during training), transfer (other agent "
        "counts) or p_alpha (target-entropy ratio)",
    )
    figure.add_argument("--budget", default="cpu", help=f"config budget: {', '.join(BUDGETS)} (default cpu)")
    figure.add_argument("--seeds", type=_positive_int, default=3, help="seeds 0..N-1 (default 3)")
    figure.add_argument(
        "--folder",
        default="results",
        help="results folder; runs go to <folder>/figures/NAME (default results)",
    )
    figure.add_argument("--jobs", type=_positive_int, default=1, help="training processes at a time")
    figure.add_argument(
        "--out", help="PNG file (default <folder>/figures/NAME.png); .csv and .json beside it"
    )
    figure.add_argument(
        "--presets",
        nargs="+",
        help="methods (default: ctc HGAT models and twins, transfer Table 1, alpha and p_alpha soft_hgrn)",
    )
    figure.add_argument(
        "--ratios",
        nargs="+",
        type=float,
        help="p_alpha: target-entropy ratios (default 0.05 0.1 0.2 0.3 0.5)",
    )
    figure.add_argument(
        "--threads", type=_positive_int, help="torch threads per process (default 1 if jobs > 1)"
    )
    figure.add_argument(
        "--save-freq", type=_positive_int, help="checkpoint every this many agent-steps (killed runs resume)"
    )
    _add_backend(figure)

    sweep = commands.add_parser(
        "sweep", help="train a grid of presets, seeds and argument values on one env, and summarise it"
    )
    sweep.add_argument("--env", required=True, help=ENV_HELP)
    sweep.add_argument("--budget", default="cpu", help=f"config budget: {', '.join(BUDGETS)} (default cpu)")
    sweep.add_argument("--presets", nargs="+", help="presets (default: the grid file's, else soft_hgrn)")
    sweep.add_argument("--seeds", type=_positive_int, help="seeds 0..N-1 (default: the grid file's, else 3)")
    sweep.add_argument(
        "--timesteps", type=_positive_int, help="agent-steps of training per run (default: the budget's)"
    )
    sweep.add_argument(
        "--grid",
        nargs="+",
        action="extend",
        default=[],
        metavar="KEY=V1,V2",
        help="algorithm argument and its values (e.g. learning_rate=1e-3,3e-4 batch_size=32,64)",
    )
    sweep.add_argument(
        "--env-grid",
        nargs="+",
        action="extend",
        default=[],
        metavar="KEY=V1,V2",
        help="env argument and its values (e.g. n_agents=10,20)",
    )
    sweep.add_argument(
        "--grid-file", help="YAML file with presets, seeds, grid, env_grid, params, env_params (docs/cli.md)"
    )
    sweep.add_argument(
        "--param",
        nargs="+",
        action="extend",
        default=[],
        metavar="KEY=VALUE",
        help="algorithm argument of every point (as train's --param)",
    )
    _add_env_params(sweep)
    _add_config(sweep)
    sweep.add_argument(
        "--folder", default="sweeps", help="runs go to <folder>/<point>/<env>/<preset>/seed_<seed>"
    )
    sweep.add_argument("--jobs", type=_positive_int, default=1, help="runs at a time")
    sweep.add_argument("--threads", type=_positive_int, help="torch threads per run (default 1 if jobs > 1)")
    sweep.add_argument(
        "--save-freq", type=_positive_int, help="checkpoint every this many agent-steps (killed runs resume)"
    )
    _add_backend(sweep)
    _add_tune_parser(commands)
    return parser


def _add_tune_parser(commands: argparse._SubParsersAction) -> None:
    """The ``tune`` subcommand: an Optuna search of one preset's hyperparameters on one env."""
    tune = commands.add_parser("tune", help="search the hyperparameters of one preset on one env (Optuna)")
    tune.add_argument("--env", required=True, help=ENV_HELP)
    tune.add_argument("--preset", required=True, help="a name of sb3_hgrn.presets.PRESETS (docs/presets.md)")
    tune.add_argument("--budget", default="cpu", help=f"config budget: {', '.join(BUDGETS)} (default cpu)")
    tune.add_argument(
        "--seed",
        type=int,
        default=0,
        help="seed of every trial's run (and of the sampler without --sampler-seed)",
    )
    tune.add_argument(
        "--timesteps", type=_positive_int, help="agent-steps of training per trial (default: the budget's)"
    )
    tune.add_argument(
        "--param",
        nargs="+",
        action="extend",
        default=[],
        metavar="KEY=VALUE",
        help="fixed algorithm argument",
    )
    _add_env_params(tune)
    _add_config(tune)
    tune.add_argument("--search-space", metavar="FILE", help="YAML search space (default: the packaged one)")
    tune.add_argument(
        "--n-trials", type=_positive_int, default=10, help="trials this command runs (default 10)"
    )
    tune.add_argument("--n-jobs", type=_positive_int, default=1, help="worker processes (default 1)")
    tune.add_argument(
        "--n-startup-trials", type=_positive_int, default=5, help="random trials before TPE (default 5)"
    )
    tune.add_argument(
        "--sampler-seed",
        type=int,
        help="seed of the TPE sampler (default --seed; one per machine sharing a study)",
    )
    tune.add_argument("--pruner", default="median", help="median (default), halving or none")
    tune.add_argument(
        "--n-warmup-steps",
        type=int,
        help="agent-steps of a trial before the median pruner may stop it (default: a third of training)",
    )
    tune.add_argument(
        "--eval-freq",
        type=_positive_int,
        help="agent-steps between evaluations (default: a fifth of training)",
    )
    tune.add_argument("--eval-episodes", type=_positive_int, default=4, help="team episodes per evaluation")
    tune.add_argument("--storage", help="Optuna storage URL (default sqlite:///<tune folder>/study.db)")
    tune.add_argument("--study-name", help="default <env>_<preset>_<budget>")
    tune.add_argument("--folder", default="tune", help="root of tune folders (<folder>/<study name>)")
    tune.add_argument("--threads", type=_positive_int, default=1, help="torch threads per worker (default 1)")
    tune.add_argument("--device", default="auto", help="torch device (default auto)")
    tune.add_argument("--verbose", type=int, default=1, help="0: quiet, 1: Optuna's log and each evaluation")


def _set_threads(threads: int | None) -> None:
    if threads is not None:
        import torch

        torch.set_num_threads(threads)


def _train_config(args: argparse.Namespace) -> RunConfig:
    """The run configuration of parsed ``train`` arguments."""
    from sb3_hgrn.experiments.config import resolve_config

    return resolve_config(
        args.env,
        args.preset,
        args.budget,
        args.seed,
        args.timesteps,
        params=parse_assignments(args.param, "--param"),
        env_params=parse_assignments(args.env_param, "--env-param"),
        config_file=args.config,
        keep_checkpoints=args.keep_checkpoints,
    )


def train_config(argv: Sequence[str]) -> RunConfig | None:
    """The run configuration of the command line ``sb3-hgrn ARGV`` when it is a ``train``, else None;
    bad arguments raise :class:`ConfigError`."""
    if not argv or argv[0] != "train":
        return None
    try:
        args = build_parser().parse_args(list(argv))
    except SystemExit as error:  # argparse has printed why
        raise ConfigError(f"Malformed train arguments: {' '.join(argv)}") from error
    return _train_config(args)


def _train_single_agent(args: argparse.Namespace) -> int:
    """``train`` with a single-agent preset: a Gymnasium env id and ``hyperparams/<preset>.yml``."""
    from sb3_hgrn.experiments.single_agent import single_agent_run_folder, train_single_agent

    if args.budget != "cpu":
        raise ConfigError(
            f"--budget applies to graph envs; the {args.preset} preset trains the n_timesteps of "
            f"hyperparams/{args.preset}.yml for the env (or --timesteps), got --budget {args.budget}."
        )
    _set_threads(args.threads)
    folder = single_agent_run_folder(args.folder, args.env, args.preset, args.seed)
    results = train_single_agent(
        args.preset,
        args.env,
        args.seed,
        folder,
        timesteps=args.timesteps,
        params={
            **parse_assignments(args.param, "--param"),
            "env_kwargs": parse_assignments(args.env_param, "--env-param"),
        },
        config_files=args.config or (),
        overwrite=args.overwrite,
        verbose=args.verbose,
        device=args.device,
    )
    print(
        f"{args.preset} on {args.env} (seed {args.seed}): return {results['mean']:.2f} "
        f"+- {results['std']:.2f} over {results['n_episodes']} episodes after {results['env_steps']} "
        f"env steps ({results['wall_time_s']:.0f} s); run folder {folder}"
    )
    return 0


def _train(args: argparse.Namespace) -> int:
    from sb3_hgrn.experiments.run_folder import run_folder
    from sb3_hgrn.experiments.runs import train_run
    from sb3_hgrn.experiments.single_agent import is_single_agent_preset

    if is_single_agent_preset(args.preset):
        return _train_single_agent(args)
    config = _train_config(args)
    _set_threads(args.threads)
    folder = run_folder(args.folder, config.env, config.preset, config.seed)
    results = train_run(
        config,
        folder,
        verbose=args.verbose,
        progress_bar=args.progress_bar,
        save_freq=args.save_freq,
        device=args.device,
        log_interval=args.log_interval,
        overwrite=args.overwrite,
        save_replay_buffer=args.save_replay_buffer,
        trust_config=args.trust_config,
    )
    print(
        f"{config.preset} on {config.env} (budget {config.budget}, seed {config.seed}): team return "
        f"{results['mean']:.2f} +- {results['std']:.2f} over {results['n_episodes']} episodes after "
        f"{results['agent_steps']} agent-steps ({results['wall_time_s']:.0f} s); run folder {folder}"
    )
    return 0


def _evaluate(args: argparse.Namespace) -> int:
    from sb3_hgrn.experiments.runs import evaluate_run

    if not 0.0 <= args.epsilon <= 1.0:
        raise ConfigError(f"--epsilon must lie in [0, 1], got {args.epsilon}.")
    _set_threads(args.threads)
    results = evaluate_run(
        args.path,
        n_episodes=args.episodes,
        deterministic=args.deterministic,
        epsilon=args.epsilon,
        env=args.env,
        n_envs=args.n_envs,
        seed=args.seed,
        trust_config=args.trust_config,
        trust_pickle=args.trust_pickle,
        online=args.online,
        critic=args.critic,
        **parse_assignments(args.env_param, "--env-param"),
    )
    print(
        f"team return {results['mean']:.2f} +- {results['std']:.2f} over {results['n_episodes']} episodes "
        f"({results['actions']} actions, epsilon {args.epsilon:g}; acting: {results['network']})"
    )
    if args.actions:
        used = [
            f"{action}: {share:.3f}" for action, share in enumerate(results["action_frequencies"]) if share
        ]
        print("actions (fraction of agent-steps): " + ", ".join(used))
    return 0


def _render(args: argparse.Namespace) -> int:
    from sb3_hgrn.experiments.render import render_run

    if args.fps <= 0:
        raise ConfigError(f"--fps must be positive, got {args.fps}.")
    n_frames = render_run(
        args.path,
        args.out,
        steps=args.steps,
        fps=args.fps,
        deterministic=args.deterministic,
        env=args.env,
        seed=args.seed,
        trust_config=args.trust_config,
        trust_pickle=args.trust_pickle,
        **parse_assignments(args.env_param, "--env-param"),
    )
    print(f"wrote {args.out} ({n_frames} frames rendered)")
    return 0


def _reproduce(args: argparse.Namespace) -> int:
    from sb3_hgrn.experiments.table1 import run_sweep

    failed = run_sweep(
        args.budget,
        n_seeds=args.seeds,
        folder=args.folder,
        jobs=args.jobs,
        presets=args.presets,
        envs=args.envs,
        threads=args.threads,
        save_freq=args.save_freq,
        backend=_backend(args),
    )
    return _report_failures(failed)


def _figure(args: argparse.Namespace) -> int:
    from sb3_hgrn.experiments.figures import make_figure

    failed = make_figure(
        args.name,
        args.budget,
        n_seeds=args.seeds,
        folder=args.folder,
        jobs=args.jobs,
        out=args.out,
        presets=args.presets,
        ratios=args.ratios,
        threads=args.threads,
        save_freq=args.save_freq,
        backend=_backend(args),
    )
    return _report_failures(failed)


def _sweep(args: argparse.Namespace) -> int:
    from sb3_hgrn.experiments.sweep import SweepSettings, assignments, parse_grid, read_grid_file, run_grid

    spec = read_grid_file(args.grid_file) if args.grid_file else {}
    settings = SweepSettings(
        args.env,
        args.budget,
        args.timesteps,
        params=parse_assignments([*assignments(list(spec.get("params", {}).items())), *args.param]),
        env_params=parse_assignments(
            [*assignments(list(spec.get("env_params", {}).items())), *args.env_param], "--env-param"
        ),
        config=args.config or [],
    )
    failed = run_grid(
        settings,
        args.presets or spec.get("presets") or ["soft_hgrn"],
        n_seeds=args.seeds or spec.get("seeds", 3),
        grid={**spec.get("grid", {}), **parse_grid(args.grid)},
        env_grid={**spec.get("env_grid", {}), **parse_grid(args.env_grid, "--env-grid")},
        folder=args.folder,
        jobs=args.jobs,
        threads=args.threads,
        save_freq=args.save_freq,
        backend=_backend(args),
    )
    return _report_failures(failed)


def _tune(args: argparse.Namespace) -> int:
    try:
        from sb3_hgrn.experiments import tune
    except ImportError as error:
        raise ConfigError(f"tune needs optuna ({error}): pip install 'sb3_hgrn[tune]'.") from error

    setup = tune.TuneSetup(
        args.env,
        args.preset,
        args.budget,
        args.seed,
        tune.load_search_space(args.preset, args.search_space),
        params=parse_assignments(args.param, "--param"),
        env_params=parse_assignments(args.env_param, "--env-param"),
        timesteps=args.timesteps,
        eval_freq=args.eval_freq,
        eval_episodes=args.eval_episodes,
        config=args.config or [],
    )
    warmup = args.n_warmup_steps
    if warmup is None:
        warmup = setup.run_config({}).total_timesteps // 3
    study_name = args.study_name or setup.default_study_name()
    folder = Path(args.folder) / study_name
    try:
        study = tune.run_study(
            setup,
            folder,
            args.n_trials,
            n_jobs=args.n_jobs,
            storage=args.storage,
            study_name=study_name,
            pruner=tune.make_pruner(args.pruner, args.n_startup_trials, warmup),
            n_startup_trials=args.n_startup_trials,
            sampler_seed=args.sampler_seed,
            threads=args.threads,
            device=args.device,
            verbose=args.verbose,
        )
    except tune.AllTrialsFailed as error:
        print(f"tune: {error}", file=sys.stderr)
        return 1
    print(tune.summary(study, folder))
    return 0


def _report_failures(failed: list) -> int:
    """Print the runs that failed; the exit status: 1 if any failed, else 0."""
    if failed:
        print(f"{len(failed)} run(s) failed: " + ", ".join(job.label() for job in failed))
    return 1 if failed else 0


COMMANDS = {
    "train": _train,
    "evaluate": _evaluate,
    "render": _render,
    "reproduce": _reproduce,
    "figure": _figure,
    "tune": _tune,
    "sweep": _sweep,
}


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line ``argv`` (default ``sys.argv[1:]``); returns the exit status.

    Bad input (unknown env, preset or budget, a malformed ``--param``, a model file it will not load)
    exits with status 2 and a message naming the problem, as argparse does for its own errors.
    """
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return COMMANDS[args.command](args)
    except (ConfigError, ModelFileError) as error:
        parser.error(str(error))
    return 2  # not reached: parser.error exits


if __name__ == "__main__":
    sys.exit(main())
