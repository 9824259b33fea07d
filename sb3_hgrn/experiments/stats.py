"""Robust statistics of few-run results with the ``rliable`` package (Agarwal et al., NeurIPS 2021).

Scores are ``(runs, tasks)`` arrays: one row per run (seed), one column per task (env). Intervals are
rliable's percentile confidence intervals from a stratified bootstrap: the runs of each task are
resampled with replacement, the tasks kept. rliable draws its resamples from numpy's global random
generator, so every estimate here seeds it with :data:`BOOTSTRAP_SEED` first (and restores its state
afterwards): an estimate depends on its own scores only, and is the same on every call.

rliable is optional (``pip install 'sb3_hgrn[stats]'``); without it these functions raise
:class:`~sb3_hgrn.experiments.config.ConfigError` naming that command.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from types import ModuleType

import numpy as np

from sb3_hgrn.experiments.config import ConfigError

INSTALL_COMMAND = "pip install 'sb3_hgrn[stats]'"
BOOTSTRAP_REPS = 2000
"""Bootstrap resamples per interval."""
CONFIDENCE = 0.95
BOOTSTRAP_SEED = 0


@dataclass(frozen=True)
class Interval:
    """A point estimate and its confidence interval ``[low, high]``."""

    estimate: float
    low: float
    high: float


@dataclass(frozen=True)
class Profile:
    """A performance profile: at each threshold ``tau``, the fraction of runs scoring above it, with
    its confidence interval ``[low, high]`` (arrays of ``taus``' length)."""

    taus: np.ndarray
    fraction: np.ndarray
    low: np.ndarray
    high: np.ndarray


def rliable_modules() -> tuple[ModuleType, ModuleType]:
    """rliable's ``library`` and ``metrics`` modules; a :class:`ConfigError` naming the install
    command when rliable is not installed."""
    try:
        from rliable import library, metrics
    except ImportError as error:
        raise ConfigError(f"Robust statistics need the rliable package: {INSTALL_COMMAND}") from error
    return library, metrics


@contextmanager
def seeded_global_numpy(seed: int) -> Iterator[None]:
    """Seed numpy's global random generator (rliable's bootstrap draws from it); restore it after."""
    state = np.random.get_state()
    np.random.seed(seed)
    try:
        yield
    finally:
        np.random.set_state(state)


def bootstrap_interval(
    scores: np.ndarray | tuple[np.ndarray, ...],
    statistic: Callable[..., float],
    reps: int = BOOTSTRAP_REPS,
) -> Interval:
    """``statistic(scores)`` with its stratified-bootstrap interval (rliable's ``get_interval_estimates``).

    :param scores: a ``(runs, tasks)`` array, or a tuple of them (``statistic`` takes one argument
        per array), each resampled on its own (e.g. the runs of two methods).
    :param reps: bootstrap resamples.
    """
    library, _ = rliable_modules()
    with seeded_global_numpy(BOOTSTRAP_SEED):
        points, intervals = library.get_interval_estimates(
            {"scores": scores},
            lambda *arrays: np.array([statistic(*arrays)]),
            reps=reps,
            confidence_interval_size=CONFIDENCE,
        )
    (low,), (high,) = intervals["scores"]
    return Interval(float(points["scores"][0]), float(low), float(high))


def iqm(scores: np.ndarray) -> float:
    """Interquartile mean of all ``scores`` (rliable's ``aggregate_iqm``): the mean once a quarter of
    the scores is cut at each end, as many as a quarter of their count rounded down; of fewer than 4
    scores nothing is cut and it is the mean."""
    return float(rliable_modules()[1].aggregate_iqm(scores))


def iqm_interval(scores: np.ndarray, reps: int = BOOTSTRAP_REPS) -> Interval:
    """IQM of ``(runs, tasks)`` scores with its stratified-bootstrap interval."""
    return bootstrap_interval(scores, iqm, reps)


def probability_of_improvement(scores_x: np.ndarray, scores_y: np.ndarray) -> float:
    """P(X > Y) (ties count half) of a run of X against a run of Y on the same task, averaged over
    tasks (rliable's ``probability_of_improvement``, the Mann-Whitney U statistic per task)."""
    return float(rliable_modules()[1].probability_of_improvement(scores_x, scores_y))


def improvement_interval(scores_x: np.ndarray, scores_y: np.ndarray, reps: int = BOOTSTRAP_REPS) -> Interval:
    """Probability of improvement of X over Y with its interval (each method's runs resampled on
    their own, per task); ``scores_x`` and ``scores_y`` have the same tasks, any number of runs."""
    return bootstrap_interval((scores_x, scores_y), probability_of_improvement, reps)


def normalise(scores: np.ndarray, low: np.ndarray, high: np.ndarray) -> np.ndarray:
    """``(scores - low) / (high - low)`` per task (column): ``low`` maps to 0, ``high`` to 1."""
    return (scores - low) / (high - low)


def run_fractions(scores: np.ndarray, taus: np.ndarray) -> np.ndarray:
    """Fraction of all ``scores`` above each threshold of ``taus``: rliable's score distribution
    (``library.score_distributions``), computed for all thresholds at once instead of one by one."""
    return (scores.reshape(-1, 1) > taus.reshape(1, -1)).mean(axis=0)


def performance_profiles(
    scores: Mapping[str, np.ndarray], taus: np.ndarray, reps: int = BOOTSTRAP_REPS
) -> dict[str, Profile]:
    """Performance profiles (score distributions over all runs of all tasks) with their stratified-
    bootstrap intervals, from rliable's ``create_performance_profile``, per key of ``scores``."""
    library, _ = rliable_modules()
    with seeded_global_numpy(BOOTSTRAP_SEED):
        curves, intervals = library.create_performance_profile(
            dict(scores),
            taus,
            custom_profile_func=run_fractions,
            reps=reps,
            confidence_interval_size=CONFIDENCE,
        )
    return {key: Profile(taus, curves[key], *intervals[key]) for key in scores}
