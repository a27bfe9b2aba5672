"""The dm_control suite's own episode limits, checked before any work: past its step limit a suite
environment silently restarts from a new initial state, so a longer episode would splice two together."""

from __future__ import annotations

from collections.abc import Mapping
from functools import cache
from typing import Any

from mftcn_bench.core.errors import SpecError


@cache
def step_limit(domain: str, task: str) -> int:
    """Control steps in one episode of the suite's `domain`/`task` before it resets itself."""
    from mftcn_bench.sim.rendering import ensure_gl

    ensure_gl()
    from dm_control import suite

    env = suite.load(domain, task)
    # dm_control keeps the limit on a private attribute; it is time_limit / control_timestep.
    return int(env._step_limit)


def check_episode_fits(domain: str, task: str, control_steps: int, what: str) -> None:
    """Refuse `control_steps` per episode beyond the suite's limit, in one line naming `what` to change."""
    limit = step_limit(domain, task)
    if control_steps > limit:
        raise SpecError(f"{what}: {control_steps} control steps per episode, but {domain}-{task} episodes end "
                        f"after {limit} (dm_control's time limit); use at most {limit}")


def check_dataset_fits(domain: str, task: str, dataset: Mapping[str, Any], what: str) -> None:
    """Refuse a data set whose episodes (`episode_length` frames, each `action_repeat` control steps apart)
    outlast the suite's limit; values of the wrong type are left to the data set's own check."""
    length, repeat = dataset.get("episode_length"), dataset.get("action_repeat", 1)
    if not isinstance(length, int) or not isinstance(repeat, int):
        return
    limit = step_limit(domain, task)
    if length * repeat > limit:
        raise SpecError(f"{what}: episode_length x action_repeat = {length} x {repeat} = {length * repeat} control "
                        f"steps per episode, but {domain}-{task} episodes end after {limit} (dm_control's time "
                        f"limit; a longer episode would be two spliced together); use at most {limit}")
