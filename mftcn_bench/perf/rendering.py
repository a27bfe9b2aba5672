"""The rendering figure: the harness's renderer against dm_control's default render at the same camera and size."""

from __future__ import annotations

from mftcn_bench.perf.fixtures import control_task
from mftcn_bench.perf.timing import BenchRow, Sizes, Target, alternate, timed


def bench_render(sizes: Sizes, task: str = "swingup") -> BenchRow:
    """Frames/s of the harness's renderer (the task's camera, size and render settings) against
    dm_control's `physics.render` at the same camera and size with the suite's default quality."""
    from mftcn_bench.sim.rendering import MultiViewRenderer, ensure_gl

    ensure_gl()  # before dm_control is imported: it picks its GL backend then
    from dm_control import suite

    env_config = control_task(task, "true-state").env_config
    h, w, camera = env_config.height, env_config.width, env_config.camera
    ours = suite.load(env_config.domain, env_config.task, task_kwargs={"random": 0})
    default = suite.load(env_config.domain, env_config.task, task_kwargs={"random": 0})
    renderer = MultiViewRenderer(ours.physics, [camera], h, w, env_config.render)
    quality = default.physics.model.vis.quality
    n = sizes.render_frames

    def render_ours() -> None:
        for _ in range(n):
            renderer.render()

    def render_default() -> None:
        for _ in range(n):
            default.physics.render(h, w, camera_id=camera)

    rates = alternate({"ours": timed(render_ours, n), "default": timed(render_default, n)}, sizes.render_rounds)
    return BenchRow(f"rendering {w}x{h} '{camera}' ({task}), frames/s", rates["ours"], "frames/s",
                    f"dm_control defaults (shadow {quality.shadowsize}, {quality.offsamples}x MSAA)",
                    rates["default"], rates["ours"] / rates["default"], Target(">=", 10),
                    f"ours: {env_config.render}, buffer {w}x{h}")
