"""`mftcn-bench diagnose coverage|probe|policy`: the diagnostics of `mftcn_bench.diagnose`, printed.

`add_diagnose_parser` adds their parsers to the main command line; each parser names its handler. The
computing lives in `mftcn_bench.diagnose`; this module parses, calls it and prints its dataclasses.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING, Any

from mftcn_bench.cli.options import common, print_table, seed
from mftcn_bench.core.home import BenchHome

if TYPE_CHECKING:  # the diagnostics import numpy, torch and MuJoCo: only the command that runs loads them
    from mftcn_bench.diagnose.coverage import CoverageFractions
    from mftcn_bench.diagnose.state_probe import ProbeScore
    from mftcn_bench.run.plan import RunRequest


def _cameras(text: str) -> list[str]:
    return [name.strip() for name in text.split(",") if name.strip()]


def _count(text: str) -> int:
    try:
        return int(text)
    except ValueError:  # argparse names the option and ends in the parser's one-line error
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None


def _run_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--encoder", required=True, help="encoder name, as given to `mftcn-bench run`")
    parser.add_argument("--task", required=True, help="task name, as given to `mftcn-bench run`")
    parser.add_argument("--preset", help="task preset (default: the task's own)")
    parser.add_argument("--seed", type=seed, default=0)


def add_diagnose_parser(commands: argparse._SubParsersAction) -> None:
    """Add `diagnose coverage|probe|policy` to `commands`."""
    diagnose = commands.add_parser("diagnose", help="diagnostics: camera coverage of a cartpole data set, the "
                                                    "state probe by camera, a stored policy's cart range")
    # the main parser's class, so that bad arguments here are its one-line exit-2 errors too
    actions = diagnose.add_subparsers(dest="diagnose_command", required=True, parser_class=type(diagnose))

    cover = actions.add_parser("coverage", help="where the cart is in each camera's image of a cartpole data set: "
                                                "|x| and the fractions of frames with the cart cut, its centre "
                                                "outside, the pole's tip outside")
    cover.add_argument("dataset", help="a collected cartpole data set folder (<home>/datasets/<name>-<id>)")
    cover.add_argument("--cameras", type=_cameras, help="comma-separated cameras (default: the data set's)")
    cover.set_defaults(handler=cmd_coverage)

    probe = actions.add_parser("probe", help="R^2 of the state probe on each camera's embedding, on the test "
                                             "split (and on random-action episodes)")
    _run_options(probe)
    probe.add_argument("--cameras", type=_cameras, help="comma-separated cameras (default: every camera of the "
                                                        "task's data set)")
    probe.add_argument("--random-episodes", type=_count, default=0, metavar="N",
                       help="also score N episodes of uniformly random actions (tasks whose data are an expert's "
                            "demonstrations: cheetah)")
    common(probe)
    probe.set_defaults(handler=cmd_probe)

    policy = actions.add_parser("policy", help="a finished cartpole run's policy replayed on its test episodes: "
                                               "cart range, camera coverage and the state probe on its states")
    _run_options(policy)
    policy.add_argument("--episodes", type=_count, default=8, help="test episodes to replay (default 8)")
    common(policy)
    policy.set_defaults(handler=cmd_policy)


def cmd_coverage(args: argparse.Namespace) -> None:
    from mftcn_bench.data.dataset import MultiViewDataset
    from mftcn_bench.diagnose.coverage import dataset_coverage

    found = dataset_coverage(MultiViewDataset(Path(args.dataset)), args.cameras)
    cart = found.cart
    print(f"{found.dataset_id}: {found.frames} frames at {found.width}x{found.height}; |x| median "
          f"{cart.median:.3f}, 90th percentile {cart.p90:.3f}, max {cart.max:.3f}")
    print_table([_coverage_row(c) for c in found.cameras])


def _coverage_row(fractions: CoverageFractions) -> dict[str, Any]:
    return {"camera": fractions.camera, "cart cut by the edge": fractions.cart_cut,
            "cart centre outside": fractions.cart_centre_out, "pole tip outside": fractions.tip_out}


def _request(args: argparse.Namespace) -> RunRequest:
    from mftcn_bench.run.plan import RunRequest

    return RunRequest(args.encoder, args.task, args.preset, args.seed)


def cmd_probe(args: argparse.Namespace) -> None:
    from mftcn_bench.diagnose.state_probe import probe_cameras

    found = probe_cameras(_request(args), BenchHome.resolve(args.home), args.cameras, args.random_episodes,
                          show_progress=not args.no_progress)
    first = found.cameras[0]
    print(f"{found.encoder} on {found.task} (preset {found.preset}, seed {found.seed}): the state probe of each "
          f"camera's embedding, fitted on {first.train_frames} train frames; R^2 on {first.test.frames} test "
          f"frames" + (f" and on {found.random_episodes} random-action episodes ({first.random_actions.frames} "
                       f"frames)" if first.random_actions is not None else ""))
    columns: list[tuple[str, ProbeScore]] = []
    for camera in found.cameras:
        columns.append((f"{camera.camera}: test", camera.test))
        if camera.random_actions is not None:
            columns.append((f"{camera.camera}: random actions", camera.random_actions))
    print_table(_score_rows(found.dimensions, columns))


def _score_rows(dimensions: tuple[str, ...], columns: list[tuple[str, ProbeScore]]) -> list[dict[str, Any]]:
    """One row per state dimension and one of their means, a column of R^2 per (label, ProbeScore)."""
    rows = [{"R^2": name, **{label: s.r2[i] for label, s in columns}} for i, name in enumerate(dimensions)]
    return rows + [{"R^2": "mean", **{label: s.mean for label, s in columns}}]


def cmd_policy(args: argparse.Namespace) -> None:
    from mftcn_bench.diagnose.policy_range import replay_policy

    found = replay_policy(_request(args), BenchHome.resolve(args.home), args.episodes,
                          show_progress=not args.no_progress)
    print(f"{found.encoder} on {found.task} (preset {found.preset}, seed {found.seed}), run {found.run_id}: "
          f"{found.episodes} test episodes, {found.frames} frames")
    print("returns replayed: " + " ".join(f"{r:.1f}" for r in found.returns_replayed))
    print("returns stored:   " + " ".join(f"{r:.1f}" for r in found.returns_stored))
    cart = found.cart
    print(f"|x| median {cart.median:.3f}, 90th percentile {cart.p90:.3f}, max {cart.max:.3f}")
    print(f"{found.camera.camera} at {found.width}x{found.height}:")
    print_table([_coverage_row(found.camera)])
    if found.probe is None or found.probe_test is None:
        print(found.probe_note)
        return
    print(f"state probe of the {found.camera.camera!r} camera's embedding, fitted on the data set's train split:")
    print_table(_score_rows(found.dimensions, [(f"test split ({found.probe_test.frames} frames)", found.probe_test),
                                                (f"policy's states ({found.probe.frames} frames)", found.probe)]))
