"""Statistics over seeds: mean, sample standard deviation, and (with 3 seeds or more) the interquartile
mean with a percentile-bootstrap confidence interval (rliable's, `results.intervals`, as the scorecard's).

Every figure that aggregates seeds goes through `seed_stats`, so reports, leaderboards and plots agree on
one rule. The bootstrap draws from a fixed seed: the same values always give the same interval. Numbers are
printed by `format_number`: to a number of decimals (returns: one) or of significant digits (errors).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
from scipy import stats as scipy_stats

from mftcn_bench.results.intervals import aggregates

STD_KIND = "sample std over seeds (ddof=1)"
IQM_MIN_SEEDS = 3             # below this the interquartile mean and its interval are not given
IQM_TRIM = 0.25               # cut this fraction from each end: the interquartile mean (rliable's too)


@dataclass(frozen=True)
class SeedStats:
    """One metric over seeds. `std` is the sample standard deviation (ddof=1), None for one seed; `iqm`,
    `ci_low`, `ci_high` are None below IQM_MIN_SEEDS seeds."""

    n: int
    mean: float
    std: float | None
    iqm: float | None = None
    ci_low: float | None = None
    ci_high: float | None = None


def iqm(values: Sequence[float]) -> float:
    """Interquartile mean: the mean after cutting a quarter of the values from each end."""
    return float(scipy_stats.trim_mean(np.asarray(values, dtype=float), IQM_TRIM))


def bootstrap_iqm_ci(values: Sequence[float]) -> tuple[float, float]:
    """Percentile-bootstrap interval of the interquartile mean (rliable: one task, its runs resampled),
    deterministic for the spec's seed."""
    data = np.asarray(values, dtype=float)
    if np.ptp(data) == 0:  # every resample is the same value
        return float(data[0]), float(data[0])
    estimate = aggregates({"values": data[:, None]})["values"].iqm
    return estimate.low, estimate.high


def seed_stats(values: Iterable[float | None]) -> SeedStats | None:
    """Statistics of one metric's per-seed values; None values (metric not applicable) and NaN are left
    out; None when nothing is left."""
    data = [float(v) for v in values if v is not None and not math.isnan(float(v))]
    if not data:
        return None
    n = len(data)
    mean = float(np.mean(data))
    std = float(np.std(data, ddof=1)) if n >= 2 else None
    if n < IQM_MIN_SEEDS:
        return SeedStats(n, mean, std)
    low, high = bootstrap_iqm_ci(data)
    return SeedStats(n, mean, std, iqm(data), low, high)


def format_number(value: float, decimals: int | None = None, significant: int = 3) -> str:
    """`value` to `decimals` decimals, or (None) to `significant` significant digits: 611.7, 0.000612, 1.64,
    35.1."""
    if decimals is not None:
        return f"{value:.{decimals}f}"
    if value == 0 or not math.isfinite(value):
        return f"{value:g}"
    places = max(significant - 1 - math.floor(math.log10(abs(value))), 0)
    return f"{round(value, places):.{places}f}"


def format_mean_std(s: SeedStats | None, decimals: int | None = 4, pm: str = "±", significant: int = 3) -> str:
    """'mean ± std' (or 'mean' for one seed, '-' for none), by `format_number`."""
    if s is None:
        return "-"
    text = format_number(s.mean, decimals, significant)
    return text if s.std is None else f"{text} {pm} {format_number(s.std, decimals, significant)}"


def format_iqm(s: SeedStats | None, decimals: int | None = 4, significant: int = 3) -> str:
    """'iqm [low, high]' or '-' below IQM_MIN_SEEDS seeds."""
    if s is None or s.iqm is None:
        return "-"
    return "{} [{}, {}]".format(*(format_number(v, decimals, significant) for v in (s.iqm, s.ci_low, s.ci_high)))
