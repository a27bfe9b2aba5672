"""How a task's results are ranked and printed: its spec's `[leaderboard]` table (metric, direction, label,
precision), which is not part of a run's config, so it never changes a run's id."""

from __future__ import annotations

from dataclasses import dataclass

from mftcn_bench.core import registry
from mftcn_bench.core.errors import BenchError, SpecError
from mftcn_bench.results.stats import SeedStats, format_iqm, format_mean_std


@dataclass(frozen=True)
class Ranking:
    """How a task's results are ranked: the metric, its direction, its printed name and precision (`decimals`
    when given, else `significant` digits: see `stats.format_number`)."""

    metric: str
    higher_is_better: bool
    label: str
    decimals: int | None = None
    significant: int = 3

    def format(self, stats: SeedStats | None) -> str:
        return format_mean_std(stats, self.decimals, significant=self.significant)

    def format_iqm(self, stats: SeedStats | None) -> str:
        return format_iqm(stats, self.decimals, significant=self.significant)


def ranking(task: str) -> Ranking | None:
    """The task spec's `[leaderboard]` table, or None when it has none or the task is not installed."""
    try:
        table = dict(registry.get("tasks", task).spec.leaderboard)
    except BenchError:
        return None
    if not table:
        return None
    metric = table.get("metric")
    if not isinstance(metric, str) or not isinstance(table.get("higher_is_better"), bool):
        raise SpecError(f"task spec {task!r}: [leaderboard] needs metric = \"<name>\" and "
                        f"higher_is_better = true/false")
    decimals, significant = table.get("decimals"), table.get("significant", 3)
    if not (decimals is None or isinstance(decimals, int)) or not isinstance(significant, int):
        raise SpecError(f"task spec {task!r}: [leaderboard] decimals and significant must be integers")
    return Ranking(metric, table["higher_is_better"], str(table.get("label", metric)), decimals, significant)
