"""Interval estimates, all through rliable (Agarwal et al. 2021): the interquartile mean and mean of a score
matrix [runs, tasks] with stratified-bootstrap confidence intervals, the probability of improvement of one
method over another, and performance profiles. The per-task boards (one task: the plain bootstrap over seeds)
and the scorecard (many tasks) share these, so a board's interval and a scorecard's follow one rule.

The settings (resamples, seed, confidence) are the scorecard spec's `[intervals]` table
(`reports/scorecard.toml`); the bootstrap draws from a fixed seed, so the same values give the same interval.
"""

from __future__ import annotations

import contextlib
import functools
import importlib.resources
import warnings
from collections.abc import Iterator, Mapping
from dataclasses import dataclass

import numpy as np

from mftcn_bench.core.specs import parse_table, parse_toml

SPEC_PACKAGE = "mftcn_bench"


@dataclass(frozen=True)
class IntervalSettings:
    """The `[intervals]` table of the scorecard spec."""

    bootstrap_reps: int
    bootstrap_seed: int
    confidence: float


@functools.cache
def scorecard_spec() -> dict:
    """`reports/scorecard.toml` as data (shipped in the package as `specs/reports/scorecard.toml`)."""
    resource = importlib.resources.files(SPEC_PACKAGE) / "specs" / "reports" / "scorecard.toml"
    return parse_toml(resource.read_text(encoding="utf-8"), "specs/reports/scorecard.toml")


def settings() -> IntervalSettings:
    return parse_table(IntervalSettings, "the scorecard spec", "intervals", scorecard_spec().get("intervals", {}))


@dataclass(frozen=True)
class Estimate:
    """A point estimate with its confidence interval."""

    value: float
    low: float
    high: float


@dataclass(frozen=True)
class Aggregates:
    """The interquartile mean and the mean of one method's score matrix, each with its interval."""

    iqm: Estimate
    mean: Estimate


@contextlib.contextmanager
def _seeded(seed: int) -> Iterator[None]:
    """numpy's global generator seeded for the block, then restored: rliable's stratified resampling draws
    from it (`np.random.choice`), whatever `random_state` it is given."""
    saved = np.random.get_state()
    np.random.seed(seed)
    try:
        with warnings.catch_warnings():  # arch's notice that RandomState is deprecated: rliable passes one
            warnings.simplefilter("ignore", FutureWarning)
            yield
    finally:
        np.random.set_state(saved)


def _estimates(score_dict: Mapping[str, object], func) -> tuple[dict, dict]:
    from rliable import library as rly

    config = settings()
    with _seeded(config.bootstrap_seed):
        return rly.get_interval_estimates(dict(score_dict), func, reps=config.bootstrap_reps,
                                          confidence_interval_size=config.confidence,
                                          random_state=np.random.RandomState(config.bootstrap_seed))


def _iqm_and_mean(scores: np.ndarray) -> np.ndarray:
    from rliable import metrics

    return np.array([metrics.aggregate_iqm(scores), metrics.aggregate_mean(scores)])


def aggregates(scores: Mapping[str, np.ndarray]) -> dict[str, Aggregates]:
    """Per method, IQM and mean over every run of every task of its matrix [runs, tasks], with
    stratified-bootstrap intervals (runs resampled within each task)."""
    matrices = {name: np.asarray(m, dtype=float).reshape(len(m), -1) for name, m in scores.items()}
    points, intervals = _estimates(matrices, _iqm_and_mean)
    out = {}
    for name in matrices:
        (iqm, mean), ((iqm_low, mean_low), (iqm_high, mean_high)) = points[name], intervals[name]
        out[name] = Aggregates(Estimate(float(iqm), float(iqm_low), float(iqm_high)),
                               Estimate(float(mean), float(mean_low), float(mean_high)))
    return out


def improvement_probability(x: np.ndarray, y: np.ndarray) -> Estimate:
    """P(X > Y) of a run of method x over a run of method y on the same task, averaged over tasks (the
    Mann-Whitney statistic), for score matrices [runs, tasks] with the same tasks in the same order."""
    from rliable import metrics

    key = "x,y"
    points, intervals = _estimates({key: (np.asarray(x, float), np.asarray(y, float))},
                                   metrics.probability_of_improvement)
    low, high = np.ravel(intervals[key])
    return Estimate(float(points[key]), float(low), float(high))


def performance_profiles(scores: Mapping[str, np.ndarray], taus: np.ndarray) -> tuple[dict, dict]:
    """Per method the fraction of its runs (all tasks) with a score above each tau, and its interval."""
    from rliable import library as rly

    config = settings()
    matrices = {name: np.asarray(m, dtype=float).reshape(len(m), -1) for name, m in scores.items()}
    with _seeded(config.bootstrap_seed):
        return rly.create_performance_profile(matrices, taus, reps=config.bootstrap_reps,
                                              confidence_interval_size=config.confidence)
