"""`mftcn-bench bench`: its flags, and the table, notes and summary it prints (and writes with --out).

The figures and how they are measured live in `mftcn_bench.perf` (`perf.bench` names and runs them).
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from datetime import UTC, datetime
from pathlib import Path

from mftcn_bench.perf.bench import FIGURES, ON_DEVICE_ONLY, run_bench
from mftcn_bench.perf.timing import FULL, QUICK, format_table, one_thread


def add_command(commands: argparse._SubParsersAction) -> None:
    """Add `bench` to the main command line."""
    bench = commands.add_parser("bench", help="speed benchmarks, each a ratio against a reference run beside it")
    bench.add_argument("--quick", action="store_true", help="CI sizes: about a minute or two on 2 cores")
    bench.add_argument("--out", help="also write the table, with the machine it ran on, to this markdown file")
    bench.add_argument("--only", help=f"comma-separated figures (default all; 'device' only on a GPU): "
                                      f"{', '.join(FIGURES)}")
    bench.add_argument("--device", help="the device of the 'device' figures, against the CPU (default "
                                        "$MFTCN_BENCH_DEVICE or auto)")
    bench.set_defaults(handler=cmd_bench)


def cmd_bench(args: argparse.Namespace) -> None:
    """Run the figures, print the table, its notes and a summary; with --out also write them to a file."""
    from mftcn_bench.core.device import requested_device, resolve_device
    from mftcn_bench.sim.rendering import ensure_gl, follow_device, gl_renderer

    placement = resolve_device(requested_device(args.device))
    follow_device(placement.device)
    ensure_gl()
    one_thread()
    sizes = QUICK if args.quick else FULL
    only = ([name.strip() for name in args.only.split(",")] if args.only else
            [f for f in FIGURES if f not in ON_DEVICE_ONLY or placement.is_cuda])
    began = time.monotonic()
    rows = run_bench(sizes, only, progress=lambda line: print(f"bench {line}", file=sys.stderr, flush=True),
                     placement=placement)
    table = format_table(rows)
    print(table)
    notes = list(dict.fromkeys(f"- {row.figure}: {row.note}" for row in rows if row.note))  # once per figure
    print("\n".join(notes))
    met = sum(row.met is True for row in rows)
    missed = [row.figure for row in rows if row.met is False]
    summary = f"{met} of {sum(row.met is not None for row in rows)} targets met ({sizes.name} sizes, " \
              f"{time.monotonic() - began:.0f} s)" + (f"; not met: {'; '.join(missed)}" if missed else "")
    summary += f"\ndevice: {placement.device}" + (f" ({placement.gpu})" if placement.gpu else "") + \
               f"; GL renderer: {gl_renderer()}"
    print(summary)
    if args.out:
        text = (f"# mftcn-bench bench ({sizes.name})\n\n{machine_description()}\n\n{table}\n\n"
                + "\n".join(notes) + f"\n\n{summary}\n")
        Path(args.out).write_text(text)
        print(f"wrote {args.out}")


def machine_description() -> str:
    """One paragraph: date, CPU, cores, memory, load and library versions (for the report's header)."""
    import mujoco
    import torch
    import torchrl

    from mftcn_bench.core.provenance import versions

    mem_kib = next(int(line.split()[1]) for line in Path("/proc/meminfo").read_text().splitlines()
                   if line.startswith("MemTotal"))
    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    lib = versions()
    return (f"{datetime.now(UTC):%Y-%m-%d %H:%M} UTC; {lib['cpu']}, {os.cpu_count()} cores, {mem_kib / 2**20:.0f} GiB; "
            f"load average {load}; python {platform.python_version()}, torch {torch.__version__} "
            f"({torch.get_num_threads()} thread), torchrl {torchrl.__version__}, mujoco {mujoco.__version__}, "
            f"dm_control {lib.get('dm-control', lib.get('dm_control', '?'))}; MUJOCO_GL={os.environ.get('MUJOCO_GL')}")
