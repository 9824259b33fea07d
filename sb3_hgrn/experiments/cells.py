"""A results table's cells: the figures of one cell's seed scores (mean and spread, IQM interval)
and how the tables print numbers, shared by Table 1, the figures' tables and the sweeps."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from sb3_hgrn.experiments.stats import Interval, iqm_interval


def mean_std(values: list[float]) -> tuple[float | None, float | None]:
    """Mean and (population) standard deviation; ``None`` for no values, and std ``None`` for one."""
    if not values:
        return None, None
    return float(np.mean(values)), float(np.std(values)) if len(values) > 1 else None


def iqm_columns(values: list[float], reps: int | None) -> dict[str, float | None]:
    """``iqm``, ``iqm_low``, ``iqm_high`` of one cell's seed scores (``None`` without scores or ``reps``)."""
    interval = iqm_interval(np.array(values).reshape(-1, 1), reps) if values and reps else None
    return interval_columns("iqm", interval)


def interval_columns(name: str, interval: Interval | None) -> dict[str, float | None]:
    """``{name, name_low, name_high}`` of ``interval`` (``None`` each when there is none)."""
    values = (None, None, None) if interval is None else (interval.estimate, interval.low, interval.high)
    return dict(zip((name, f"{name}_low", f"{name}_high"), values, strict=True))


def format_interval(
    estimate: float | None, low: float | None, high: float | None, number: Callable[[float], str]
) -> str:
    """``estimate [low, high]``, ``-`` when missing."""
    if estimate is None or low is None or high is None:
        return "-"
    return f"{number(estimate)} [{number(low)}, {number(high)}]"


def format_number(value: float) -> str:
    return f"{value:.0f}" if abs(value) >= 100 else f"{value:.1f}"


def format_cell(mean: float | None, std: float | None) -> str:
    """``mean +- std``, the mean alone when there is no spread to show, ``-`` when missing."""
    if mean is None:
        return "-"
    return format_number(mean) if std is None else f"{format_number(mean)} +- {format_number(std)}"


def rounded(rows: Sequence[dict[str, Any]], digits: int = 4) -> list[dict[str, Any]]:
    """``rows`` with their floats rounded to ``digits`` decimals (for the CSV files)."""
    return [{key: round(v, digits) if isinstance(v, float) else v for key, v in row.items()} for row in rows]
