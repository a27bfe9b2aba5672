"""Progress of a long step (an encoder's fit, PPO, an expert's training): the callback type the steps call,
and a terminal bar that serves as one."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager

# progress(done, total, {"loss": ...}): steps or batches done of `total`, with the latest statistics.
Progress = Callable[[int, int, dict[str, float]], None]


@contextmanager
def progress_bar(desc: str, unit: str, enabled: bool = True) -> Iterator[Progress]:
    """A `Progress` drawing a tqdm bar on stderr where tqdm shows one (a terminal), none when not `enabled`
    (`--no-progress`); the bar is closed when the block ends, however it ends."""
    from tqdm import tqdm

    bar = tqdm(desc=desc, unit=unit, disable=None if enabled else True, leave=False)

    def report(done: int, total: int, stats: dict[str, float]) -> None:
        bar.total, bar.n = total, done
        bar.set_postfix({k: f"{v:.4g}" for k, v in stats.items()}, refresh=False)
        bar.refresh()

    try:
        yield report
    finally:
        bar.close()
