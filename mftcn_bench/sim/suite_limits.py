"""The dm_control suite's own episode limits, checked before any work: past its step limit a suite
environment silently restarts from a new initial state, so a longer episode would splice two together."""

from __future__ import annotations

from functools import cache

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
