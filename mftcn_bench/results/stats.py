"""Statistics over seeds: mean, sample standard deviation, and (with 3 seeds or more) the interquartile
mean with a percentile-bootstrap 95% confidence interval.

Every figure that aggregates seeds goes through `seed_stats`, so reports, leaderboards and plots agree on
one rule. The bootstrap draws from a fixed seed: the same values always give the same interval.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
from scipy import stats as scipy_stats

STD_KIND = "sample std over seeds (ddof=1)"
IQM_MIN_SEEDS = 3             # below this the interquartile mean and its interval are not given
IQM_TRIM = 0.25               # cut this fraction from each end: the interquartile mean
CONFIDENCE = 0.95
BOOTSTRAP_RESAMPLES = 10_000
BOOTSTRAP_SEED = 0


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


def _iqm_axis(sample: np.ndarray, axis: int = -1) -> np.ndarray:
    return scipy_stats.trim_mean(sample, IQM_TRIM, axis=axis)


def bootstrap_iqm_ci(values: Sequence[float], confidence: float = CONFIDENCE,
                     resamples: int = BOOTSTRAP_RESAMPLES, seed: int = BOOTSTRAP_SEED) -> tuple[float, float]:
    """Percentile-bootstrap interval of the interquartile mean, deterministic for a given seed."""
    data = np.asarray(values, dtype=float)
    if np.ptp(data) == 0:  # every resample is the same value
        return float(data[0]), float(data[0])
    result = scipy_stats.bootstrap((data,), _iqm_axis, n_resamples=resamples, confidence_level=confidence,
                                   method="percentile", vectorized=True, rng=np.random.default_rng(seed))
    return float(result.confidence_interval.low), float(result.confidence_interval.high)


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


def format_mean_std(s: SeedStats | None, decimals: int = 4, pm: str = "±") -> str:
    """'mean ± std' (or 'mean' for one seed, '-' for none)."""
    if s is None:
        return "-"
    text = f"{s.mean:.{decimals}f}"
    return text if s.std is None else f"{text} {pm} {s.std:.{decimals}f}"


def format_iqm(s: SeedStats | None, decimals: int = 4) -> str:
    """'iqm [low, high]' or '-' below IQM_MIN_SEEDS seeds."""
    if s is None or s.iqm is None:
        return "-"
    return f"{s.iqm:.{decimals}f} [{s.ci_low:.{decimals}f}, {s.ci_high:.{decimals}f}]"
