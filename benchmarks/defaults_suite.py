"""Candidate defaults on a suite of nine many-agent envs, 3 seeds each, normalised over the suite.

Run: python benchmarks/defaults_suite.py --folder sweeps/suite [--candidates default gs2:gradient_steps=2]
     [--presets soft_hgrn dqn dgn] [--seeds 3] [--envs surviving_v0 ...] [--equal-time-to soft_hgrn]
     [--report-only]

A candidate is a name and the algorithm arguments it sets over the library defaults
(``NAME:KEY=VALUE,KEY=VALUE``; ``default`` sets none). For each candidate and each env of
:data:`SUITE` the script runs ``sb3-hgrn sweep`` at the env's ``cpu`` budget (one run at a time, one
torch thread; finished runs are kept and skipped), then evaluates the uniformly random policy on the
same evaluation episodes. It prints, per env, each (candidate, preset)'s mean +- std of the saved
models' evaluations and their mean CPU seconds of training per run, and over the suite the IQM of the runs'
normalised scores with its 95 % stratified-bootstrap interval: Random is 0 and the best mean of the
table on that env is 1 (the ``dqn`` preset is near Random on some envs, so it cannot be the unit).

``--equal-time-to PRESET`` adds, per candidate and env, a run of every other preset at the budget that
costs it the reference preset's mean CPU seconds of training: its agent-steps times the reference's
CPU seconds over its own. Each such run sets its schedules (exploration, learning starts) for its own
budget, as a user with that much time would; its runs and column are named ``CANDIDATE-time-PRESET``.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sb3_hgrn.experiments.config import random_policy_config
from sb3_hgrn.experiments.run_folder import read_eval, run_folder
from sb3_hgrn.experiments.runs import evaluate_random_policy
from sb3_hgrn.experiments.stats import iqm_interval


@dataclass(frozen=True)
class SuiteEnv:
    """One env of the suite: its short ``name``, the ``env`` argument of the CLI and its config file."""

    name: str
    env: str
    config: str | None = None


SUITE = (
    SuiteEnv("surviving_v0", "surviving_v0"),
    SuiteEnv("pursuit_v0", "pursuit_v0"),
    SuiteEnv("uav_mbs_v0", "uav_mbs_v0"),
    SuiteEnv("ctc_v0", "ctc_v0"),
    SuiteEnv("battle_magent2", "examples.battle_magent2:make_env", "examples/configs/battle_magent2.yml"),
    SuiteEnv("spread_mpe2", "examples.spread_mpe2:make_env", "examples/configs/spread_mpe2.yml"),
    SuiteEnv("kaz_pettingzoo", "examples.kaz_pettingzoo:make_env", "examples/configs/kaz_pettingzoo.yml"),
    SuiteEnv("tag_mpe2", "examples.tag_mpe2:make_env", "examples/configs/tag_mpe2.yml"),
    SuiteEnv(
        "pursuit_magent2",
        "examples.adversarial_pursuit_magent2:make_env",
        "examples/configs/adversarial_pursuit_magent2.yml",
    ),
)
"""The four paper envs at their ``cpu`` budget, then five third-party envs through the examples' glue."""

BUDGET = "cpu"


@dataclass(frozen=True)
class Candidate:
    """A named set of algorithm arguments (``KEY=VALUE`` strings, as the CLI's ``--param``)."""

    name: str
    params: tuple[str, ...]

    @classmethod
    def parse(cls, text: str) -> Candidate:
        name, _, assignments = text.partition(":")
        params = tuple(item for item in assignments.split(",") if item)
        if not name or any("=" not in item for item in params):
            raise ValueError(f"--candidates: expected NAME or NAME:KEY=VALUE,KEY=VALUE, got {text!r}")
        return cls(name, params)


def sweep_root(folder: Path, candidate: Candidate, env: SuiteEnv) -> Path:
    """Where the sweep of ``candidate`` on ``env`` keeps its runs (its one grid point, ``default``)."""
    return folder / candidate.name / env.name / "default"


def run_sweep(
    folder: Path,
    candidate: Candidate,
    env: SuiteEnv,
    presets: list[str],
    seeds: int,
    timesteps: int | None = None,
) -> None:
    """``sb3-hgrn sweep`` of ``presets`` x ``seeds`` with ``candidate``'s arguments on ``env`` (at
    ``timesteps`` agent-steps per run where given, else the budget's)."""
    command = [sys.executable, "-m", "sb3_hgrn", "sweep", "--env", env.env, "--budget", BUDGET,
               "--presets", *presets, "--seeds", str(seeds), "--jobs", "1", "--threads", "1",
               "--folder", str(folder / candidate.name / env.name)]  # fmt: skip
    if timesteps is not None:
        command += ["--timesteps", str(timesteps)]
    if env.config:
        command += ["--config", env.config]
    if candidate.params:
        command += ["--param", *candidate.params]
    subprocess.run(command, check=True)


def random_scores(folder: Path, env: SuiteEnv, seeds: int) -> np.ndarray:
    """``(seeds,)`` mean team returns of the uniformly random policy, evaluated once and kept."""
    scores = []
    for seed in range(seeds):
        run = folder / "random" / env.name / f"seed_{seed}"
        result = read_eval(run) or evaluate_random_policy(
            random_policy_config(env.env, BUDGET, seed, env.config), run
        )
        scores.append(result["mean"])
    return np.array(scores)


def run_results(
    folder: Path, candidate: Candidate, env: SuiteEnv, preset: str, seeds: int
) -> tuple[np.ndarray, np.ndarray] | None:
    """``(seeds,)`` evaluation means and CPU seconds of training of one (candidate, env, preset), or
    ``None`` while any seed is unfinished."""
    results = [
        read_eval(run_folder(sweep_root(folder, candidate, env), env.env, preset, seed))
        for seed in range(seeds)
    ]
    if any(result is None for result in results):
        return None
    cpu_seconds = [r.get("train_cpu_s", np.nan) for r in results]  # runs before it was recorded: nan
    return np.array([r["mean"] for r in results]), np.array(cpu_seconds)


def time_candidate(candidate: Candidate, preset: str) -> Candidate:
    """``preset``'s equal-time runs of the candidate: the same arguments, their own folder (one budget
    per sweep folder) and column."""
    return Candidate(f"{candidate.name}-time-{preset}", candidate.params)


def run_equal_time(
    folder: Path, candidate: Candidate, env: SuiteEnv, reference: str, presets: list[str], seeds: int
) -> None:
    """Run each of ``presets`` at the agent-steps that cost it ``reference``'s mean CPU seconds of
    training on ``env`` (both measured on ``candidate``'s finished runs at the budget)."""
    reference_result = run_results(folder, candidate, env, reference, seeds)
    if reference_result is None:
        raise RuntimeError(f"--equal-time-to {reference}: its runs on {env.name} are unfinished")
    reference_seconds = float(np.mean(reference_result[1]))
    for preset in presets:
        runs = [
            read_eval(run_folder(sweep_root(folder, candidate, env), env.env, preset, seed))
            for seed in range(seeds)
        ]
        if any(run is None or "train_cpu_s" not in run for run in runs):
            raise RuntimeError(
                f"--equal-time-to: {preset} on {env.name} has no finished run with its CPU seconds"
            )
        seconds = float(np.mean([run["train_cpu_s"] for run in runs]))
        timesteps = round(float(np.mean([run["agent_steps"] for run in runs])) * reference_seconds / seconds)
        print(f"{env.name} {preset}: {timesteps} agent-steps for {reference}'s {reference_seconds:.0f} CPU s")
        run_sweep(folder, time_candidate(candidate, preset), env, [preset], seeds, timesteps)


def cell(scores: np.ndarray, cpu_seconds: np.ndarray) -> str:
    """``mean +- std (CPU s)`` of one (candidate, env, preset)'s seeds."""
    return f"{scores.mean():.1f} +- {scores.std():.1f} ({np.nanmean(cpu_seconds):.0f} s)"


def report(
    folder: Path, candidates: list[Candidate], presets: list[str], envs: list[SuiteEnv], seeds: int
) -> None:
    """Print the per-env table and the suite's normalised IQM of every (candidate, preset) with runs."""
    pairs = [(candidate, preset) for candidate in candidates for preset in presets]
    randoms = {env.name: random_scores(folder, env, seeds) for env in envs}
    results = {(env.name, c.name, p): run_results(folder, c, env, p, seeds) for env in envs for c, p in pairs}
    columns = [(c.name, p) for c, p in pairs if any(results[env.name, c.name, p] is not None for env in envs)]
    print(f"| env | Random | {' | '.join(f'{name} {preset}' for name, preset in columns)} |")
    print(f"|---|---|{'---|' * len(columns)}")
    normalised: dict[tuple[str, str], list[np.ndarray]] = {column: [] for column in columns}
    for env in envs:
        random = randoms[env.name]
        done = {column: results[(env.name, *column)] for column in columns}
        done = {column: result for column, result in done.items() if result is not None}
        cells = [cell(*done[column]) if column in done else "-" for column in columns]
        print(f"| {env.name} | {random.mean():.1f} +- {random.std():.1f} | {' | '.join(cells)} |")
        if done:
            best = max(scores.mean() for scores, _ in done.values())
            for column, (scores, _) in done.items():
                normalised[column].append((scores - random.mean()) / (best - random.mean()))
    print("\nNormalised over the envs each has run (Random 0, the best mean of the table on each env 1):")
    for (name, preset), by_env in normalised.items():
        interval = iqm_interval(np.stack(by_env, axis=1))
        print(
            f"  {name:>12s} {preset:10s} IQM {interval.estimate:6.2f} "
            f"[{interval.low:5.2f}, {interval.high:5.2f}]  over {len(by_env)} envs x {seeds} seeds"
        )


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--folder", type=Path, required=True)
    parser.add_argument("--candidates", nargs="+", default=[Candidate("default", ())], type=Candidate.parse)
    parser.add_argument("--presets", nargs="+", default=["soft_hgrn", "dqn", "dgn"])
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument(
        "--envs", nargs="+", choices=[env.name for env in SUITE], default=[e.name for e in SUITE]
    )
    parser.add_argument(
        "--equal-time-to", metavar="PRESET", help="also run the other presets for PRESET's CPU seconds"
    )
    parser.add_argument(
        "--report-only", action="store_true", help="print the tables of the runs already done"
    )
    args = parser.parse_args()
    envs = [env for env in SUITE if env.name in args.envs]
    others = [preset for preset in args.presets if preset != args.equal_time_to]
    if args.equal_time_to and args.equal_time_to not in args.presets:
        parser.error(f"--equal-time-to {args.equal_time_to}: not among --presets {args.presets}")
    if not args.report_only:
        for candidate in args.candidates:
            for env in envs:
                run_sweep(args.folder, candidate, env, args.presets, args.seeds)
                if args.equal_time_to:
                    run_equal_time(args.folder, candidate, env, args.equal_time_to, others, args.seeds)
    candidates = list(args.candidates)
    if args.equal_time_to:
        candidates += [
            time_candidate(candidate, preset) for candidate in args.candidates for preset in others
        ]
    report(args.folder, candidates, args.presets, envs, args.seeds)


if __name__ == "__main__":
    main()
