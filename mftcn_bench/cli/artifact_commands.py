"""Commands that make or move artifacts other than results: `expert train` pins a demonstrations' expert in
the project, `expert demos` its demonstrations; `runs export` / `runs import` move an unfinished run to another
home."""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from mftcn_bench.core.errors import BenchError
from mftcn_bench.core.home import BenchHome

if TYPE_CHECKING:
    from mftcn_bench.tasks.base import RecordsExpert


def add_commands(commands: argparse._SubParsersAction, common: Callable[[argparse.ArgumentParser], None],
                 parser_class: type[argparse.ArgumentParser]) -> None:
    """Add `expert train|demos` and `runs export|import` to `commands`."""
    expert = commands.add_parser("expert", help="the true-state experts that demonstration data sets are "
                                                "recorded from")
    expert_commands = expert.add_subparsers(dest="expert_command", required=True, parser_class=parser_class)
    train = expert_commands.add_parser(
        "train", help="train the expert of a task's preset and pin it in the project (experts/): its data sets "
                      "are then recorded from that file on every machine")
    train.add_argument("--task", required=True, help="a task recorded from an expert: cheetah, imitate-swingup, ...")
    train.add_argument("--preset", help="the preset whose [expert_ppo] settings to train (default: the task's own)")
    train.add_argument("--out", type=Path, help="folder for the pinned file (default: the project's experts/)")
    train.add_argument("--force", action="store_true", help="replace a pinned expert of the same settings")
    common(train)
    train.set_defaults(handler=cmd_expert_train)
    demos = expert_commands.add_parser(
        "demos", help="record the pinned expert's demonstrations of a task's preset (each frame's simulator state "
                      "and action) and pin them in the project (experts/): every machine then renders the same "
                      "episodes instead of running the expert")
    demos.add_argument("--task", required=True, help="a task recorded from an expert: cheetah, imitate-cheetah, ...")
    demos.add_argument("--preset", help="the preset whose [dataset] to record (default: the task's own)")
    demos.add_argument("--force", action="store_true", help="replace pinned demonstrations of the same settings")
    common(demos)
    demos.set_defaults(handler=cmd_expert_demos)

    runs = commands.add_parser("runs", help="move an unfinished run (its checkpoint and fitted encoder) to "
                                            "another home")
    runs_commands = runs.add_subparsers(dest="runs_command", required=True, parser_class=parser_class)
    export = runs_commands.add_parser("export", help="copy an unfinished run to DIR/<run id>/")
    export.add_argument("run_id", help="the run's id (`mftcn-bench sweep status` lists running runs)")
    export.add_argument("dir", type=Path)
    common(export)
    export.set_defaults(handler=cmd_runs_export)
    imported = runs_commands.add_parser("import", help="put an exported run into this home; the same `run` "
                                                       "command then continues it")
    imported.add_argument("dir", type=Path, help="an exported run's folder (DIR/<run id>)")
    common(imported)
    imported.set_defaults(handler=cmd_runs_import)


def _expert_task(name: str, preset: str | None) -> RecordsExpert:
    """Task `name` at `preset` (as true state sees it: the task's own config), refused unless an expert records
    its data."""
    from mftcn_bench.run.plan import RunRequest, prepare
    from mftcn_bench.tasks.base import RecordsExpert

    task = prepare(RunRequest("true-state", name, preset)).task
    if not isinstance(task, RecordsExpert):
        raise BenchError(f"task {name!r} is not recorded from an expert; tasks that are: cheetah, "
                         f"cheetah-difference, imitate-swingup, imitate-cheetah")
    return task


def cmd_expert_train(args: argparse.Namespace) -> None:
    from mftcn_bench.rl.expert import pin_expert, pinned_path, train_expert

    task = _expert_task(args.task, args.preset)
    env, ppo, seed = task.expert.env, task.expert.ppo, task.expert.seed
    target = pinned_path(env, ppo, seed, args.out)
    if target.exists() and not args.force:
        raise BenchError(f"{target} is pinned already; --force replaces it (every data set recorded from it "
                         f"then gets a new key)")
    home = BenchHome.resolve(args.home)
    trained = train_expert(home.experts, env, ppo, seed)
    pinned = pin_expert(trained, env, ppo, seed, args.out)
    sidecar = json.loads(pinned.with_suffix(".json").read_text())
    print(f"pinned {pinned} (sha256 {sidecar['sha256'][:16]}): test return {sidecar['return_mean']:.1f} +- "
          f"{sidecar['return_std']:.1f} over {sidecar['test_episodes']} episodes. Every data set recorded from "
          f"this config's expert now gets a new key: runs on them are new runs. Commit both files.")


def cmd_expert_demos(args: argparse.Namespace) -> None:
    from mftcn_bench.rl.demos import pinned_demos_path, record_demos
    from mftcn_bench.rl.expert import pinned_expert

    task = _expert_task(args.task, args.preset)
    expert, data = task.expert, task.demos_config
    weights = pinned_expert(expert.env, expert.ppo, expert.seed)
    target = pinned_demos_path(expert, data)
    if weights is None or target is None:
        raise BenchError(f"task {args.task!r}: its expert is not pinned; pin it first with `mftcn-bench expert "
                         f"train --task {args.task}" + (f" --preset {args.preset}`" if args.preset else "`"))
    if target.exists() and not args.force:
        raise BenchError(f"{target} is pinned already; --force replaces it (every data set rendered from it then "
                         f"gets a new key)")
    episodes = int(data["train_episodes"]) + int(data["test_episodes"])
    pinned = record_demos(expert, weights, data, episodes, target, not args.no_progress)
    sidecar = json.loads(pinned.with_suffix(".json").read_text())
    print(f"pinned {pinned} (sha256 {sidecar['sha256'][:16]}): {episodes} episodes of "
          f"{sidecar['episode_length']} frames. Every data set of these settings now renders them and gets a new "
          f"key: runs on them are new runs. Commit both files.")


def cmd_runs_export(args: argparse.Namespace) -> None:
    from mftcn_bench.run.portable import export_run

    moved = export_run(BenchHome.resolve(args.home), args.run_id, args.dir)
    print(f"exported run {moved.plan.run_id} ({moved.progress}) to {moved.folder}; on another machine: "
          f"`mftcn-bench runs import {moved.folder}`, then `{moved.plan.command()}`")


def cmd_runs_import(args: argparse.Namespace) -> None:
    from mftcn_bench.run.portable import import_run

    moved = import_run(BenchHome.resolve(args.home), args.dir)
    needs = ("it reads no data, so it continues" if moved.plan.dataset is None else
             f"it continues if this machine makes the same data set (fingerprint {moved.plan.dataset}); "
             f"otherwise the command starts another run")
    print(f"imported run {moved.plan.run_id} ({moved.progress}); continue it with `{moved.plan.command()}`: {needs}")
