"""The results commands of `mftcn-bench`: sweep, report, leaderboard, results export/import/doc, plot.

`add_commands` adds their parsers to the main command line; each parser names its handler.
"""

from __future__ import annotations

import argparse
import os
from collections.abc import Callable
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path

from tabulate import tabulate

from mftcn_bench.core.device import requested_device
from mftcn_bench.core.errors import BenchError, SpecError
from mftcn_bench.core.fileio import atomic_write_bytes
from mftcn_bench.core.home import BenchHome
from mftcn_bench.core.specs import parse_override

REPORT_CHOICES = ["probe", "swingup", "cheetah", "pouring", "pouring-attributes", "swingup-limits",
                  "swingup-160-limits", "cheetah-limits", "probe-streams", "swingup-streams", "imitate", "scorecard",
                  "all"]
PLOT_CHOICES = ["curves", "probe-lookback", "pouring-lookback"]


def _store(args: argparse.Namespace):
    from mftcn_bench.results.store import ResultStore

    return ResultStore(BenchHome.resolve(args.home).database)


def add_commands(commands: argparse._SubParsersAction, common: Callable[[argparse.ArgumentParser], None],
                 parser_class: type[argparse.ArgumentParser],
                 device_options: Callable[[argparse.ArgumentParser], None]) -> None:
    """Add sweep, report, leaderboard, results and plot to `commands`."""
    sweep = commands.add_parser("sweep", help="run a grid of encoders x tasks x seeds (local pool or Ray); "
                                              "`sweep status` shows a queue's progress")
    sweep.add_argument("action", nargs="?", choices=["status"], help="status: done / running / left of --queue "
                                                                       "NAME (of every queue without it)")
    sweep.add_argument("--encoders", help="comma-separated encoder names, e.g. mftcn1,mftcn5,pve")
    sweep.add_argument("--tasks", help="comma-separated task names, e.g. cartpole-probe")
    sweep.add_argument("--seeds", default="0", help="seeds: 0-4, 0,2,5 or 0-2,7 (default 0)")
    sweep.add_argument("--preset", help="task preset for every task (default: each task's own)")
    sweep.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                       help="override a spec value for every run (repeatable)")
    sweep.add_argument("--executor", choices=["local", "ray"], default="local")
    sweep.add_argument("--address", help="Ray cluster address (ray://host:10001 or host:6379); default: a "
                                         "local Ray instance")
    sweep.add_argument("--workers", type=int, help="jobs at once (local processes, or CPUs of a local Ray "
                                                   "instance; default: one per core, or the queue's)")
    sweep.add_argument("--queue", metavar="NAME", help="record the grid in the home as queue NAME; started "
                                                       "again (`--queue NAME` alone), it continues the grid")
    sweep.add_argument("--export", metavar="DIR", help="write each run's record to DIR/<run id>.json as it is "
                                                       "stored (kept with the queue)")
    sweep.add_argument("--threads", type=int, default=1, help="torch/BLAS threads per job (default 1)")
    device_options(sweep)
    common(sweep)
    sweep.set_defaults(handler=cmd_sweep)

    report = commands.add_parser("report", help="print the paper's tables from stored results, ours beside "
                                                "the paper's")
    report.add_argument("table", choices=REPORT_CHOICES)
    report.add_argument("--preset", help="only results of this preset (default: the paper preset's, then the "
                        "quick preset's, each labelled)")
    report.add_argument("--format", choices=["markdown", "latex"], default="markdown")
    report.add_argument("--encoders", help="scorecard: only these encoders (comma-separated; the floor, "
                        "ceiling and baseline are always scored)")
    report.add_argument("--plot", metavar="PNG", help="scorecard: also write the performance profiles here")
    common(report)
    report.set_defaults(handler=cmd_report)

    board = commands.add_parser("leaderboard", help="write markdown leaderboards from stored results")
    board.add_argument("--out", default="leaderboards", help="folder to write (default ./leaderboards)")
    board.add_argument("--html", metavar="DIR", help="write the web leaderboard instead: DIR/index.html (one "
                       "self-contained page) and the run records it links to, DIR/records/")
    common(board)
    board.set_defaults(handler=cmd_leaderboard)

    results = commands.add_parser("results", help="export or import results as JSON files (one per run)")
    results_commands = results.add_subparsers(dest="results_command", required=True, parser_class=parser_class)
    export = results_commands.add_parser("export", help="write <run id>.json for every stored run")
    export.add_argument("folder")
    export.add_argument("--task")
    export.add_argument("--preset")
    common(export)
    imported = results_commands.add_parser("import", help="merge a folder of run JSON files into the store")
    imported.add_argument("folder")
    common(imported)
    doc = results_commands.add_parser("doc", help="fill a document's generated tables from a folder of run "
                                                  "records (docs/RESULTS.md from results/)")
    doc.add_argument("document")
    doc.add_argument("--records", default="results", help="folder of run JSON files (default ./results)")
    doc.add_argument("--check", action="store_true", help="exit 2 if the document is not up to date")
    results.set_defaults(handler=cmd_results)

    plot = commands.add_parser("plot", help="PNG plots from stored results")
    plot.add_argument("kind", choices=PLOT_CHOICES)
    plot.add_argument("--task", help="learning curves of this task only")
    plot.add_argument("--out", default="plots", help="folder to write (default ./plots)")
    plot.add_argument("--records", metavar="DIR", help="plot the run JSON files in DIR (results/: docs/RESULTS.md's "
                                                       "figures) instead of the home's store")
    common(plot)
    plot.set_defaults(handler=cmd_plot)


def cmd_sweep(args: argparse.Namespace) -> None:
    from mftcn_bench.orchestration.queue import SweepQueue
    from mftcn_bench.orchestration.sweep import Sweep, SweepFailed, SweepRequest, parse_names, parse_seeds, summary_rows
    from mftcn_bench.results.ranking import ranking

    home = BenchHome.resolve(args.home)
    if args.action == "status":
        return _sweep_status(home, args.queue)
    export = Path(args.export) if args.export else None
    if export is not None and not args.queue:  # the queue's listener writes the records: without one none would be
        raise SpecError(f"--export {args.export}: records are exported as a queue stores them; add --queue NAME, or "
                        "write them after the sweep with `results export DIR --task T --preset P`")
    if args.encoders is None and args.tasks is None and args.queue:  # continue a recorded grid
        recorded = SweepQueue.open(home, args.queue).request
        request = replace(recorded, workers=recorded.workers if args.workers is None else args.workers)
    elif args.encoders is None or args.tasks is None:
        raise SpecError("sweep needs --encoders and --tasks (or --queue NAME alone, to continue a recorded grid)")
    else:
        request = SweepRequest(parse_names(args.encoders, "encoders"), parse_names(args.tasks, "tasks"),
                               parse_seeds(args.seeds), args.preset,
                               tuple(parse_override(o) for o in args.overrides), args.executor, args.address,
                               (os.cpu_count() or 1) if args.workers is None else args.workers, args.threads,
                               requested_device(args.device),
                               args.deterministic)
    if args.queue:
        SweepQueue.check(home, args.queue, request)
    sweep = Sweep(request, home, echo=lambda line: print(line, flush=True))  # every name checked first
    if args.queue:
        sweep.listener = SweepQueue.open(home, args.queue, request, export)
    jobs = sweep.run()
    metrics = {task: (r.metric if (r := ranking(task)) else None) for task in request.tasks}
    rows = summary_rows(jobs, metrics.get)
    print(tabulate([list(r.values()) for r in rows], headers=list(rows[0]), tablefmt="github",
                   disable_numparse=True))
    counts = {s: sum(j.status == s for j in jobs) for s in ("done", "reused", "failed")}
    print(f"{len(jobs)} jobs: {counts['done']} done, {counts['reused']} reused, {counts['failed']} failed")
    if counts["failed"]:
        raise SweepFailed(f"{counts['failed']} of {len(jobs)} sweep jobs failed (see the table above); a rerun "
                          f"redoes only those")


def _sweep_status(home: BenchHome, name: str | None) -> None:
    from mftcn_bench.orchestration.queue import queue_status

    names = [name] if name else sorted(p.stem for p in (home.root / "queues").glob("*.json"))
    if not names:
        print(f"no queues in {home.root / 'queues'} (`sweep ... --queue NAME` records one)")
    for queue in names:
        status = queue_status(home, queue)
        print(f"queue {queue}:")
        if status.rows:
            print(tabulate([list(r.values()) for r in status.rows], headers=list(status.rows[0]),
                           tablefmt="github", disable_numparse=True))
        print(status.summary())


def cmd_report(args: argparse.Namespace) -> None:
    from mftcn_bench.results.paper_tables import TABLES
    from mftcn_bench.results.report import report

    if args.table == "scorecard":
        _scorecard(args)
        return
    if args.encoders or args.plot:
        raise SpecError(f"--encoders and --plot are options of `report scorecard`, not of `report {args.table}`")
    names = list(TABLES) if args.table == "all" else [args.table]
    print(report(_store(args), names, args.preset, args.format))


def _scorecard(args: argparse.Namespace) -> None:
    from mftcn_bench.core import registry
    from mftcn_bench.results import scorecard

    if args.format != "markdown":
        raise SpecError("report scorecard prints markdown only (--format markdown)")
    encoders = None
    if args.encoders:
        encoders = [name.strip() for name in args.encoders.split(",") if name.strip()]
        for name in encoders:
            registry.get("encoders", name)  # an unknown name: one line with suggestions, before any work
    card = scorecard.build(_store(args).query(), args.preset or "paper", encoders)
    print(scorecard.render(card))
    if args.plot:
        written = scorecard.plot_profiles(card, Path(args.plot))
        print(f"\nperformance profiles: {written}" if written else "\nno performance profiles: no encoder has an "
              "aggregate at this preset")


def cmd_leaderboard(args: argparse.Namespace) -> None:
    from mftcn_bench.results.leaderboard import write_boards

    if args.html:
        from mftcn_bench.results.site import write_site

        print(f"wrote {write_site(_store(args).query(), Path(args.html))}")
        return
    written = write_boards(_store(args).query(), Path(args.out))
    print(f"wrote {len(written)} files to {args.out}: {', '.join(p.name for p in written)}")


def cmd_results(args: argparse.Namespace) -> None:
    from mftcn_bench.results.records_io import export_results, import_results

    if args.results_command == "doc":
        return _fill_document(Path(args.document), Path(args.records), args.check)
    store, folder = _store(args), Path(args.folder)
    if args.results_command == "export":
        count = export_results(store, folder, args.task, args.preset)
        print(f"exported {count} runs to {folder}")
    else:
        summary = import_results(store, folder)
        print(f"imported from {folder}: {summary.added} added, {summary.updated} updated, "
              f"{summary.unchanged} already stored")


@contextmanager
def _store_of(folder: Path):
    """A temporary store holding the run JSON files of `folder` (`results export`; the project's results/)."""
    import tempfile

    from mftcn_bench.results.records_io import import_results
    from mftcn_bench.results.store import ResultStore

    if not folder.is_dir():
        raise SpecError(f"records folder {folder} does not exist; give a folder of run JSON files, such as results")
    with tempfile.TemporaryDirectory() as tmp:
        store = ResultStore(Path(tmp) / "results.sqlite")
        import_results(store, folder)
        yield store


def _fill_document(document: Path, records: Path, check: bool) -> None:
    from mftcn_bench.results.document import fill_generated

    if not document.is_file():
        raise SpecError(f"no document {document}")
    with _store_of(records) as store:
        text = document.read_text(encoding="utf-8")
        filled = fill_generated(text, store)
    if check:
        if filled != text:
            raise BenchError(f"{document} is not up to date with {records}; run `mftcn-bench results doc {document}`")
        print(f"{document} is up to date with {records}")
        return
    atomic_write_bytes(document, filled.encode())
    print(f"wrote {document} from the records in {records}")


def cmd_plot(args: argparse.Namespace) -> None:
    from mftcn_bench.results import plots

    if args.records:
        with _store_of(Path(args.records)) as store:
            records = store.query()
    else:
        records = _store(args).query()
    out = Path(args.out)
    if args.kind == "curves":
        written = plots.plot_curves(records, out, args.task)
    elif args.kind == "probe-lookback":
        written = plots.plot_probe_lookback(records, out)
    else:
        written = plots.plot_pouring_lookback(records, out)
    if not written:
        print(f"nothing to plot: no stored runs of the current specs for `plot {args.kind}`")
    for path in written:
        print(f"wrote {path}")
