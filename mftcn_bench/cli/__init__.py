"""The `mftcn-bench` command line: run, list, data, check, sweep, report, leaderboard, results, plot, diagnose,
expert, runs, bench.

The results commands (sweep to plot) live in `results_commands`, `diagnose` in `diagnose_commands`, `expert`
and `runs` in `artifact_commands`, `bench` in `bench_command`; what they share in `options`.

Bad input ends with one line on stderr naming what was wrong and what is allowed, and exit code 2.
"""

from __future__ import annotations

import argparse
import errno
import sys
import warnings
from collections.abc import Sequence
from pathlib import Path

from mftcn_bench.cli.options import Parser, add_device_options, common, print_table, seed
from mftcn_bench.core.allocator import keep_freed_memory
from mftcn_bench.core.device import CHOICES, requested_device
from mftcn_bench.core.errors import BenchError
from mftcn_bench.core.home import ENV_VAR, BenchHome
from mftcn_bench.core.specs import parse_override

DEFAULT_ENCODER = "mftcn4"
DEFAULT_TASK = "cartpole-probe"


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(prog="mftcn-bench", description=__doc__.splitlines()[0])
    commands = parser.add_subparsers(dest="command", required=True, parser_class=Parser)

    run = commands.add_parser("run", help="run one encoder on one task and print its result")
    run.add_argument("--encoder", default=DEFAULT_ENCODER, help=f"encoder name (default {DEFAULT_ENCODER})")
    run.add_argument("--task", default=DEFAULT_TASK, help=f"task name (default {DEFAULT_TASK})")
    run.add_argument("--preset", help="task preset: smoke, quick or paper (default: the task's own)")
    run.add_argument("--seed", type=seed, default=0)
    run.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                     help="override a spec value, e.g. encoder.embedding_dim=8 (repeatable)")
    run.add_argument("--force", action="store_true", help="recompute even if a stored result exists")
    add_device_options(run)
    common(run)

    listing = commands.add_parser("list", help="list registered encoders or tasks")
    listing.add_argument("kind", choices=["encoders", "tasks"])

    data = commands.add_parser("data", help="datasets")
    data_commands = data.add_subparsers(dest="data_command", required=True, parser_class=Parser)
    collect = data_commands.add_parser("collect", help="collect the dataset a task needs")
    collect.add_argument("task", help="task whose dataset to collect, e.g. cartpole-probe")
    collect.add_argument("--preset")
    collect.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    common(collect)
    show = data_commands.add_parser("show", help="contact sheet (PNG) and video (mp4) of one episode, with labels")
    show.add_argument("task", help="task whose dataset to show, e.g. pouring")
    show.add_argument("--preset")
    show.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    show.add_argument("--split", default="train", choices=["train", "val", "test"])
    show.add_argument("--episode", type=int, default=0, help="position of the episode in its split (default 0)")
    show.add_argument("--columns", type=int, default=8, help="frames per view in the contact sheet")
    show.add_argument("--out", default=".", help="folder for the PNG and the mp4 (default: here)")
    common(show)

    check = commands.add_parser("check", help="check that a registered encoder keeps the encoder contract")
    check_commands = check.add_subparsers(dest="check_command", required=True, parser_class=Parser)
    check_encoder = check_commands.add_parser(
        "encoder", help="run the contract (metadata, embeddings, embed_episode, streaming, determinism, "
                        "save/load) against one encoder on a small synthetic dataset; exit 2 on a failure")
    check_encoder.add_argument("name", help="encoder name (built-in or plugin), e.g. mftcn4")
    check_encoder.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                               help="override a spec value (repeatable)")
    check_encoder.add_argument("--device", default="cpu", help=f"the device check's device: {CHOICES} "
                                                               "(default cpu)")
    check_encoder.add_argument("--keep", metavar="DIR", help="work in DIR and keep it (default: a temporary "
                                                              "folder)")

    from mftcn_bench.cli.results_commands import add_commands

    add_commands(commands, common, Parser, add_device_options)  # sweep, report, leaderboard, results, plot

    from mftcn_bench.cli.diagnose_commands import add_diagnose_parser

    add_diagnose_parser(commands)  # diagnose coverage|probe|policy

    from mftcn_bench.cli.artifact_commands import add_commands as add_artifact_commands

    add_artifact_commands(commands, common, Parser)  # expert train, runs export|import

    from mftcn_bench.cli.bench_command import add_command as add_bench

    add_bench(commands)  # bench
    return parser


def cmd_run(args: argparse.Namespace) -> None:
    from mftcn_bench.run.plan import RunRequest
    from mftcn_bench.run.runner import run

    request = RunRequest(args.encoder, args.task, args.preset, args.seed,
                         tuple(parse_override(o) for o in args.overrides), args.force,
                         requested_device(args.device), args.deterministic)
    outcome = run(request, BenchHome.resolve(args.home), show_progress=not args.no_progress)
    record = outcome.record
    how = "reused stored result" if outcome.reused else f"finished in {record.timings['total_s']:.1f} s"
    print(f"{record.encoder} on {record.task} (preset {record.preset}, seed {record.seed}): {how}; "
          f"run {record.run_id}")
    print_table(outcome.table)
    for note in outcome.notes:
        print(note)


def cmd_check(args: argparse.Namespace) -> None:
    from mftcn_bench.core import registry
    from mftcn_bench.run.conformance import check_encoder

    registry.get("encoders", args.name)  # an unknown name is the usual one-line error
    failed = 0
    for line in check_encoder(args.name, tuple(parse_override(o) for o in args.overrides),
                              Path(args.keep) if args.keep else None, args.device):
        print(line, flush=True)
        failed += line.status == "FAIL"
    if failed:
        raise BenchError(f"encoder {args.name!r} failed {failed} check{'s' if failed > 1 else ''} of the "
                         f"encoder contract (lines marked FAIL above)")
    print(f"encoder {args.name!r} keeps the encoder contract")


def cmd_list(args: argparse.Namespace) -> None:
    from mftcn_bench.core import registry

    print_table(registry.describe(args.kind))


def cmd_data(args: argparse.Namespace) -> None:
    from mftcn_bench.run.artifacts import prepare_dataset
    from mftcn_bench.run.plan import RunRequest, prepare

    overrides = tuple(parse_override(o) for o in args.overrides)
    prepared = prepare(RunRequest(DEFAULT_ENCODER, args.task, args.preset, 0, overrides))
    dataset = prepare_dataset(prepared, BenchHome.resolve(args.home), show_progress=not args.no_progress)
    if args.data_command == "show":
        from mftcn_bench.data.show import show_episode
        from mftcn_bench.tasks.base import LabelledTask

        task = prepared.task
        names, formats = (task.label_names, task.label_formats) if isinstance(task, LabelledTask) else ((), None)
        for path in show_episode(dataset, args.split, args.episode, Path(args.out), args.columns, names, formats):
            print(f"wrote {path}")
        return
    frames = sum(dataset.episode_length(i) for s in ("train", "val", "test") for i in dataset.episodes(s))
    train, test = len(dataset.episodes("train")), len(dataset.episodes("test"))
    val = f"{len(dataset.episodes('val'))} val + " if dataset.episodes("val") else ""
    print(f"dataset {dataset.config['name']} ({dataset.dataset_id}): {train} train + {val}{test} test episodes, "
          f"{frames} frames x {len(dataset.cameras)} views "
          f"at {dataset.image_shape[1]}x{dataset.image_shape[0]}, in {dataset.root}")


# The others name theirs (args.handler).
COMMANDS = {"run": cmd_run, "list": cmd_list, "data": cmd_data, "check": cmd_check}


_show_warning = warnings.showwarning


def _warn_one_line(message, category, filename, lineno, file=None, line=None) -> None:
    """The harness's warnings (plugins, a dirty source tree, a rerun) as one line; others as Python shows them."""
    from mftcn_bench.core.errors import BenchWarning

    if issubclass(category, BenchWarning):
        print(f"mftcn-bench: warning: {message}", file=sys.stderr)
    else:
        _show_warning(message, category, filename, lineno, file, line)


def _unwritable(exc: OSError) -> bool:
    """A write refused by the file system (permissions, read-only, full disk): the user's to fix."""
    return isinstance(exc, PermissionError) or exc.errno in (errno.EROFS, errno.ENOSPC, errno.EDQUOT)


def main(argv: Sequence[str] | None = None) -> int:
    warnings.showwarning = _warn_one_line
    keep_freed_memory()
    try:
        args = build_parser().parse_args(argv)
        (COMMANDS.get(args.command) or args.handler)(args)
    except BenchError as exc:
        print(f"mftcn-bench: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except OSError as exc:
        if not _unwritable(exc):
            raise
        print(f"mftcn-bench: error: cannot write {exc.filename or 'a file'} ({exc.strerror}); the results folder "
              f"must be writable and have free space: fix it or choose another with --home or ${ENV_VAR}",
              file=sys.stderr)
        return BenchError.exit_code
    except KeyboardInterrupt:
        print("mftcn-bench: interrupted; finished work is kept and a rerun continues from it",
              file=sys.stderr)
        return 130
    return 0
