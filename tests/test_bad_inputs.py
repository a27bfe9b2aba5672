"""The bad-input catalogue: every way a user can get a run wrong, each through the command line.

Each case calls `mftcn_bench.cli.main` in-process and checks the contract of the CLI: exit code 2, exactly
one line on stderr (`mftcn-bench: error: ...`) naming what was wrong and what is allowed, no traceback,
and nothing written: no result row, no run folder, no encoder checkpoint, no half-made dataset or
temporary file. A complete dataset is allowed to stay only where the problem can only show after the
data exists (a NaN loss, a plugin's embeddings). Datasets come from the synthetic collector (nothing is
rendered) and the encoders are tiny, so the whole catalogue runs in seconds.
"""

from __future__ import annotations

import ast
import contextlib
import os
import shutil
import subprocess
import sys
import textwrap
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest
import torch

from mftcn_bench.cli import main
from mftcn_bench.data.synthetic import synthetic_collector
from mftcn_bench.results.store import ResultStore
from mftcn_bench.sim import rendering

# A tiny cartpole-probe run: 3 + 1 synthetic episodes of 30 frames at 16x24, a 3-epoch probe.
TINY_TASK = ["--preset", "smoke", "--no-progress",
             "--set", "task.dataset.episode_length=30", "--set", "task.dataset.train_episodes=3",
             "--set", "task.dataset.test_episodes=1", "--set", "task.dataset.height=16",
             "--set", "task.dataset.width=24", "--set", "task.probe.epochs=3", "--set", "task.probe.hidden=[8]",
             "--set", "task.probe.batch_size=16"]
# A tiny mfTCN: 8-channel convolutions, 2 training steps on 4 time steps from 2 episodes.
TINY_MFTCN = ["--encoder", "mftcn1", *TINY_TASK,
              "--set", "encoder.model.adapter_channels=8", "--set", "encoder.model.temporal_channels=8",
              "--set", "encoder.embedding_dim=8", "--set", "encoder.train.steps=2",
              "--set", "encoder.train.checkpoint_every=0", "--set", "encoder.train.batch_timesteps=4",
              "--set", "encoder.train.episodes_per_batch=2", "--set", "encoder.train.alpha=2",
              "--set", "encoder.train.episode_pool=2"]


# ---------------------------------------------------------------------------------------------- helpers


@pytest.fixture(autouse=True)
def synthetic_data(monkeypatch):
    """cartpole-probe collects with the synthetic collector: the same arrays, nothing rendered."""
    monkeypatch.setattr("mftcn_bench.tasks.probe.collect_episode", synthetic_collector)


def snapshot(root: Path) -> dict[str, tuple[int, int]]:
    """Every file and folder under `root`: relative path (folders end in '/') -> (size, mtime_ns)."""
    out: dict[str, tuple[int, int]] = {}
    if not root.exists():
        return out
    for path in root.rglob("*"):
        stat = path.lstat()
        out[str(path.relative_to(root)) + ("/" if path.is_dir() else "")] = (stat.st_size, stat.st_mtime_ns)
    return out


def _complete_dataset_part(home: Path, rel: str) -> bool:
    """True for the datasets/ (or features/) folder itself and for files of a dataset (or a frozen base's
    feature cache, which a fit needs before its first step) whose manifest was written."""
    parts = rel.rstrip("/").split("/")
    if parts[0] not in ("datasets", "features"):
        return False
    if len(parts) == 1:
        return True
    folder = home / parts[0] / parts[1]
    complete = (folder / "manifest.json").exists() and not (folder / "progress.json").exists()
    return complete and not parts[-1].startswith(".")


def assert_nothing_written(home: Path, before: dict[str, tuple[int, int]], rows_before: int = 0,
                           dataset_ok: bool = False) -> None:
    """No new result row and no new or changed file except lock files, an empty results database, the
    (empty) encoders/ and runs/ folders and, if `dataset_ok`, a complete dataset and feature cache."""
    after = snapshot(home)
    changed = sorted(p for p in after if before.get(p) != after[p])
    allowed_always = {"encoders/", "datasets/", "runs/", "results.sqlite", "results.sqlite-wal",
                      "results.sqlite-shm"}
    unexpected = [p for p in changed if p not in allowed_always and not p.endswith(".lock")
                  and not (dataset_ok and _complete_dataset_part(home, p))]
    assert not unexpected, f"written despite the error: {unexpected}"
    assert not [p for p in after if ".tmp-" in p], "a temporary file was left behind"
    if (home / "results.sqlite").exists() and os.access(home / "results.sqlite", os.W_OK):
        assert len(ResultStore(home / "results.sqlite").query()) == rows_before
    encoders = home / "encoders"
    if encoders.exists():
        assert all(p.name.endswith(".lock") or before.get(f"encoders/{p.name}/") for p in encoders.iterdir())


def fails(capsys, argv: list[str], *needles: str) -> str:
    """Run the CLI; assert exit 2 and exactly one stderr line, an error naming every needle. Returns it.
    (The warning that a source checkout has uncommitted changes depends on the checkout, not the input.)"""
    code = main(argv)
    captured = capsys.readouterr()
    lines = [line for line in captured.err.strip().splitlines() if "source tree has uncommitted changes" not in line]
    assert code == 2, f"exit {code}; stderr: {captured.err[-2000:]}"
    assert "Traceback" not in captured.err
    assert len(lines) == 1, f"expected one line on stderr, got {lines}"
    assert lines[0].startswith("mftcn-bench: error: "), lines[0]
    for needle in needles:
        assert needle in lines[0], f"{needle!r} not in {lines[0]!r}"
    return lines[0]


def check_case(capsys, tmp_path: Path, argv: list[str], *needles: str, dataset_ok: bool = False) -> str:
    """A bad input on a fresh home: the error, and nothing written."""
    home = tmp_path / "home"
    line = fails(capsys, [*argv, "--home", str(home)] if argv[0] in ("run", "data", "report") else argv,
                 *needles)
    assert_nothing_written(home, {}, dataset_ok=dataset_ok)
    return line


@pytest.fixture(scope="module")
def built_home(tmp_path_factory) -> Path:
    """A home holding one finished tiny mftcn1 run (synthetic dataset, trained encoder, stored result)."""
    home = tmp_path_factory.mktemp("built") / "home"
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr("mftcn_bench.tasks.probe.collect_episode", synthetic_collector)
        assert main(["run", *TINY_MFTCN, "--home", str(home)]) == 0
    return home


@pytest.fixture
def finished(built_home, tmp_path) -> Path:
    """A private copy of `built_home`, to break."""
    home = tmp_path / "home"
    shutil.copytree(built_home, home)
    return home


def only(home: Path, pattern: str) -> Path:
    (found,) = sorted(home.glob(pattern))
    return found


@contextlib.contextmanager
def read_only(path: Path) -> Iterator[None]:
    """Make `path` unwritable even for root (chmod for a user, the immutable attribute for root)."""
    if os.geteuid() != 0:
        mode = path.stat().st_mode
        path.chmod(0o555 if path.is_dir() else 0o444)
        try:
            yield
        finally:
            path.chmod(mode)
        return
    if shutil.which("chattr") is None or subprocess.run(["chattr", "+i", str(path)], capture_output=True).returncode:
        pytest.skip("running as root without chattr +i: cannot make a folder read-only")
    try:
        yield
    finally:
        subprocess.run(["chattr", "-i", str(path)], check=True)


def make_plugin(root: Path, monkeypatch, *, spec: str, code: str | None, name: str = "plug-enc") -> str:
    """Install (on sys.path) a third-party package registering encoder `name` with this spec and code.
    With `code` None the package's module does not exist at all. Returns the encoder name."""
    package = f"h8plug_{uuid.uuid4().hex[:8]}"
    site = root / "site"
    dist = site / f"{package}-1.0.dist-info"
    dist.mkdir(parents=True)
    (dist / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {package}\nVersion: 1.0\n")
    (dist / "entry_points.txt").write_text(f"[mftcn_bench.encoders]\n{name} = {package}.enc:Enc\n")
    if code is not None:
        (site / package / "specs" / "encoders").mkdir(parents=True)
        (site / package / "__init__.py").write_text("")
        (site / package / "enc.py").write_text(textwrap.dedent(code))
        (site / package / "specs" / "encoders" / f"{name}.toml").write_text(textwrap.dedent(spec))
    monkeypatch.syspath_prepend(str(site))
    return name


PLUGIN_SPEC = """\
    family = "plug"
    description = "a test plugin"
    frames = 1
    stride = 1
    embedding_dim = 4
    [model]
    [train]
    """

PLUGIN_CODE = """\
    import numpy as np

    from mftcn_bench.encoders.base import EncoderInfo


    class Enc:
        needs_fit = False

        def __init__(self, spec, image_shape, seed):
            self.spec, self.image_shape = spec, tuple(image_shape)

        @property
        def info(self):
            return EncoderInfo(self.spec.name, 1, 1, self.image_shape, self.spec.embedding_dim, 0)

        def fit(self, dataset, budget, progress, workdir):
            return {{}}

        def embed(self, clips):
            n, dim = len(clips.frames), self.spec.embedding_dim
            return {output}

        def save(self, path):
            pass

        def load(self, path):
            pass
    """


# ------------------------------------------------------------------------- names, presets, overrides


SPEC_CASES = {
    "unknown encoder": (["run", "--encoder", "mftcn3"],
                        ["unknown encoder 'mftcn3'; did you mean", "valid: ", "mftcn4"]),
    "unknown task": (["run", "--task", "cartpole-prob"],
                     ["unknown task 'cartpole-prob'; did you mean cartpole-probe, cartpole-probe-agent-rate?",
                      "valid: cartpole-probe"]),
    "unknown preset": (["run", "--preset", "smok"],
                       ["unknown preset", "did you mean smoke", "valid: demo, paper, quick"]),
    "unknown override key": (["run", "--set", "encoder.embeding_dim=8"],
                             ["unknown override key 'encoder.embeding_dim'", "did you mean encoder.embedding_dim"]),
    "override of the wrong type": (["run", "--set", "encoder.embedding_dim=eight"],
                                   ['encoder.embedding_dim="eight": expected a int like 32']),
    "override that is not KEY=VALUE": (["run", "--set", "encoder.embedding_dim"], ["is not KEY=VALUE"]),
    "override of a name key": (["run", "--set", "encoder.family=tcn"],
                               ["'encoder.family' cannot be changed; choose another --encoder/--task"]),
    "override of a whole table": (["run", "--set", "task.dataset=1"],
                                  ["'task.dataset' names a table; set one of its keys instead"]),
    "negative seed": (["run", "--seed", "-1"], ["--seed must be a non-negative integer, got -1"]),
    "seed that is not an integer": (["run", "--seed", "1.5"], ["--seed must be a non-negative integer, got '1.5'"]),
    "unknown command": (["frobnicate"], ["invalid choice: 'frobnicate'", "'run'"]),
    "unknown option": (["run", "--sed", "1"], ["unrecognized arguments: --sed 1"]),
    "unknown report table": (["report", "foo"], ["argument table: invalid choice: 'foo' (choose from 'probe'"]),
    "unknown list kind": (["list", "encoder"], ["invalid choice: 'encoder' (choose from 'encoders', 'tasks')"]),
    "unknown task to collect": (["data", "collect", "nope"], ["unknown task 'nope'", "valid: cartpole-probe"]),
    "embedding size 0": (["run", "--set", "encoder.embedding_dim=0"], ["embedding_dim must be >= 1, got 0"]),
    "lookback longer than the episodes": (
        ["run", "--encoder", "mftcn29", *TINY_TASK, "--set", "task.dataset.episode_length=20"],
        ["'mftcn29' has a lookback of 29 frames", "longer than the task's 20-frame episodes",
         "lookback <= 20 or set task.dataset.episode_length >= 29"]),
    "camera the domain does not have": (["run", *TINY_TASK, "--set", 'task.dataset.cameras=["fixed", "top"]'],
                                        ["camera 'top' does not exist in cartpole; available: fixed, lookatcart"]),
    "probe camera not in the dataset": (["run", *TINY_TASK, "--set", "task.probe.camera=lookatcart",
                                         "--set", 'task.dataset.cameras=["fixed"]'],
                                        ["probe camera 'lookatcart' is not one of the dataset's cameras ['fixed']"]),
    "empty dataset (0 train episodes)": (["run", *TINY_TASK, "--set", "task.dataset.train_episodes=0"],
                                         ["at least 1 train and 1 test episode, got 0 and 1",
                                          "train_episodes and test_episodes >= 1"]),
    "image height 0": (["run", *TINY_TASK, "--set", "task.dataset.height=0"],
                       ["height must be an integer >= 1, got 0"]),
    "probe epochs 0": (["data", "collect", "cartpole-probe", "--preset", "smoke", "--set", "task.probe.epochs=0"],
                       ["task.probe.epochs must be >= 1, got 0"]),
    "probe validation fraction out of range": (["run", *TINY_TASK, "--set", "task.probe.validation_fraction=2.0"],
                                               ["validation_fraction must be in [0, 1)", "got 2.0"]),
    "probe episodes that dm_control would splice": (
        ["run", *TINY_TASK, "--set", "task.dataset.action_repeat=2", "--set", "task.dataset.episode_length=600"],
        ["[dataset]: episode_length x action_repeat = 600 x 2 = 1200 control steps per episode",
         "cartpole-swingup episodes end after 1000", "use at most 1000"]),
    "swing-up data that dm_control would splice": (
        ["run", "--task", "swingup", "--preset", "smoke", "--set", "task.dataset.action_repeat=2",
         "--set", "task.dataset.episode_length=1000"],
        ["task 'swingup': [dataset]: episode_length x action_repeat = 1000 x 2 = 2000 control steps"]),
    "a data set's frame rate the agent step does not divide": (
        ["run", "--task", "swingup", "--preset", "smoke", "--set", "task.dataset.action_repeat=3"],
        ["[env] action_repeat (8) must be a multiple of the data set's action_repeat (3)"]),
    "probe-state readout without the difference": (
        ["run", "--task", "swingup-probe-state", "--preset", "smoke", "--set", "task.env.embedding_difference=false"],
        ["the probe reads [e_t, e_t - e_t-1]; set [env] embedding_difference = true"]),
    "probe-state readout of another camera": (
        ["run", "--task", "swingup-probe-state", "--preset", "smoke", "--set", "task.probe.camera=lookatcart"],
        ["[probe] camera 'lookatcart' must be the policy's camera, [env] camera 'fixed'"]),
}


@pytest.mark.parametrize("case", list(SPEC_CASES))
def test_bad_name_preset_or_override(capsys, tmp_path, case):
    argv, needles = SPEC_CASES[case]
    check_case(capsys, tmp_path, argv, *needles)


DEVICE_CASES = {
    "unknown device": (["run", *TINY_TASK, "--device", "tpu"], ["unknown device 'tpu'", "allowed: auto, cpu, cuda"]),
    "cuda without a GPU": (["run", *TINY_TASK, "--device", "cuda"],
                           ["--device cuda", "sees no CUDA GPU", "use --device cpu or auto"]),
    "cuda:N without a GPU": (["run", *TINY_TASK, "--device", "cuda:1"], ["--device cuda:1", "sees no CUDA GPU"]),
    "sweep on cuda without a GPU": (["sweep", "--encoders", "mftcn1", "--tasks", "cartpole-probe", "--device",
                                     "cuda"], ["--device cuda", "sees no CUDA GPU"]),
    "bench on an unknown device": (["bench", "--quick", "--only", "device", "--device", "gpu0"],
                                   ["unknown device 'gpu0'"]),
}


@pytest.mark.parametrize("case", list(DEVICE_CASES))
def test_bad_device(capsys, tmp_path, monkeypatch, case):
    """Refused before any work, also on a machine that has a GPU (torch is told it has none)."""
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    argv, needles = DEVICE_CASES[case]
    if argv[0] == "sweep":
        argv = [*argv, "--home", str(tmp_path / "home")]
    check_case(capsys, tmp_path, argv, *needles)


QUEUE_CASES = {
    "sweep without a grid": (["sweep"], ["sweep needs --encoders and --tasks", "--queue NAME alone"]),
    "continuing a queue that does not exist": (["sweep", "--queue", "nope"], ["no queue 'nope'",
                                                                             "give --encoders and --tasks"]),
    "a queue name that is a path": (["sweep", "--encoders", "true-state", "--tasks", "swingup", "--queue", "../x"],
                                    ["--queue '../x'", "a plain file name"]),
    "status of a queue that does not exist": (["sweep", "status", "--queue", "nope"], ["no queue 'nope'"]),
    "an export without a queue": (["sweep", "--encoders", "true-state", "--tasks", "swingup", "--export", "out"],
                                  ["--export out", "add --queue NAME", "results export"]),
}


@pytest.mark.parametrize("case", list(QUEUE_CASES))
def test_bad_queue(capsys, tmp_path, case):
    argv, needles = QUEUE_CASES[case]
    check_case(capsys, tmp_path, [*argv, "--home", str(tmp_path / "home")], *needles)


def test_another_grid_under_a_queues_name_is_refused_and_the_queue_kept(capsys, tmp_path):
    from mftcn_bench.core.home import BenchHome
    from mftcn_bench.orchestration.queue import SweepQueue
    from mftcn_bench.orchestration.sweep import SweepRequest

    home = BenchHome.resolve(tmp_path / "home")
    SweepQueue.open(home, "grid", SweepRequest(("true-state",), ("swingup",), (0, 1), "smoke"))
    kept = (home.root / "queues" / "grid.json").read_bytes()
    fails(capsys, ["sweep", "--encoders", "true-state", "--tasks", "swingup", "--seeds", "0-2", "--preset", "smoke",
                   "--queue", "grid", "--home", str(home.root)],
          "queue 'grid' holds another grid (seeds differ)", "`sweep --queue grid` alone")
    assert (home.root / "queues" / "grid.json").read_bytes() == kept and not home.database.exists()


def test_bad_device_from_the_environment(capsys, tmp_path, monkeypatch):
    monkeypatch.setenv("MFTCN_BENCH_DEVICE", "cuda:x")
    check_case(capsys, tmp_path, ["run", *TINY_TASK], "unknown device 'cuda:x'")


def test_results_folder_that_is_a_file(capsys, tmp_path):
    home = tmp_path / "file"
    home.write_text("not a folder")
    fails(capsys, ["run", "--home", str(home)], f"results folder {home} cannot be created",
          "choose a writable one with --home or $MFTCN_BENCH_HOME")
    assert home.read_text() == "not a folder"


def test_missing_gl_library(capsys, tmp_path, monkeypatch):
    monkeypatch.setenv("MUJOCO_GL", "egl")
    monkeypatch.setattr(rendering.ctypes.util, "find_library", lambda name: None)
    check_case(capsys, tmp_path, ["run", *TINY_TASK], "MUJOCO_GL=egl needs the system library libEGL",
               "install it with: apt-get install -y libegl1")


# ------------------------------------------------------------------------------- read-only and broken stores


def test_read_only_results_folder(capsys, tmp_path):
    home = tmp_path / "home"
    home.mkdir()
    with read_only(home):
        fails(capsys, ["run", *TINY_TASK, "--home", str(home)], f"results folder {home} is not writable",
              "choose a writable one with --home")
    assert snapshot(home) == {}


def test_read_only_datasets_folder(capsys, tmp_path):
    """A write refused in the middle of a run (PermissionError) is one line, not a traceback."""
    home = tmp_path / "home"
    (home / "datasets").mkdir(parents=True)
    before = snapshot(home)
    with read_only(home / "datasets"):
        fails(capsys, ["run", *TINY_TASK, "--home", str(home)], f"cannot write {home / 'datasets'}/",
              "must be writable", "--home")
    assert_nothing_written(home, before)


def test_read_only_results_database_fails_before_any_work(capsys, finished):
    before = snapshot(finished)
    with read_only(finished / "results.sqlite"):
        fails(capsys, ["run", *TINY_MFTCN, "--seed", "1", "--home", str(finished)],
              "results database", "is read-only", "make it writable or choose another results folder")
    assert_nothing_written(finished, before, rows_before=1)
    assert not list((finished / "encoders").glob("*/model.pt"))[1:], "no second encoder was trained"


def test_results_database_that_is_not_sqlite(capsys, tmp_path):
    home = tmp_path / "home"
    home.mkdir()
    (home / "results.sqlite").write_text("not a database " * 100)
    before = snapshot(home)
    fails(capsys, ["run", *TINY_TASK, "--home", str(home)], "cannot be used (file is not a database)",
          "move it away to start a new one")
    assert snapshot(home) == before


# -------------------------------------------------------------------------------------- broken datasets


def test_chunk_with_a_bad_checksum(capsys, finished):
    chunk = only(finished, "datasets/*/ep00001.npz")
    data = bytearray(chunk.read_bytes())
    data[len(data) // 2] ^= 0xFF
    chunk.write_bytes(bytes(data))
    before = snapshot(finished)
    fails(capsys, ["run", *TINY_TASK, "--encoder", "random-state", "--home", str(finished)],
          f"dataset chunk {chunk} does not match its checksum", "delete the dataset folder")
    assert_nothing_written(finished, before, rows_before=1)


def test_missing_chunk(capsys, finished):
    chunk = only(finished, "datasets/*/ep00003.npz")
    chunk.unlink()
    before = snapshot(finished)
    fails(capsys, ["run", *TINY_TASK, "--encoder", "random-state", "--home", str(finished)],
          f"dataset chunk {chunk} is missing", "collect it again")
    assert_nothing_written(finished, before, rows_before=1)


def test_manifest_that_is_not_json(capsys, finished):
    manifest = only(finished, "datasets/*/manifest.json")
    manifest.write_text(manifest.read_text()[:100])
    before = snapshot(finished)
    fails(capsys, ["run", *TINY_TASK, "--encoder", "random-state", "--home", str(finished)],
          f"dataset manifest {manifest} is not a valid manifest (JSONDecodeError", "delete the folder")
    assert_nothing_written(finished, before, rows_before=1)


def test_dataset_whose_manifest_lists_no_episodes(capsys, finished):
    import json

    manifest = only(finished, "datasets/*/manifest.json")
    manifest.write_text(json.dumps({**json.loads(manifest.read_text()), "chunks": []}))
    before = snapshot(finished)
    fails(capsys, ["run", *TINY_TASK, "--encoder", "random-state", "--home", str(finished)],
          "is empty: its manifest lists no episodes", "delete the folder to collect it again")
    assert_nothing_written(finished, before, rows_before=1)


# --------------------------------------------------------------------------------- broken checkpoints

# Another probe setting: a new run id that reuses (loads) the trained encoder of `built_home`.
REUSE_ENCODER = [*TINY_MFTCN, "--set", "task.probe.epochs=4"]


def test_truncated_checkpoint(capsys, finished):
    model = only(finished, "encoders/mftcn1-*/model.pt")
    model.write_bytes(model.read_bytes()[:200])
    before = snapshot(finished)
    fails(capsys, ["run", *REUSE_ENCODER, "--home", str(finished)], f"encoder checkpoint {model} cannot be loaded",
          "truncated or not a torch checkpoint", "rerun with --force")
    assert_nothing_written(finished, before, rows_before=1)


def test_truncated_training_checkpoint(capsys, finished):
    workdir = only(finished, "encoders/mftcn1-*")
    (workdir / "model.pt").unlink()
    (workdir / "fit.json").unlink()
    (workdir / "train_checkpoint.pt").write_bytes(b"PK\x03\x04 cut off")
    before = snapshot(finished)
    fails(capsys, ["run", *REUSE_ENCODER, "--home", str(finished)],
          f"training checkpoint {workdir / 'train_checkpoint.pt'} cannot be loaded", "rerun with --force")
    assert_nothing_written(finished, before, rows_before=1)


class _Payload:
    """Unpickling this would create a file: a stand-in for code run by a malicious checkpoint."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (Path.touch, (self.marker,))


def test_checkpoint_with_a_pickled_object_is_refused(capsys, finished, tmp_path):
    model = only(finished, "encoders/mftcn1-*/model.pt")
    marker = tmp_path / "code-ran"
    torch.save({"model": {}, "image_shape": [16, 24], "extra": _Payload(marker)}, model)
    before = snapshot(finished)
    fails(capsys, ["run", *REUSE_ENCODER, "--home", str(finished)], f"encoder checkpoint {model} cannot be loaded",
          "holds pickled Python objects, which are never loaded")
    assert not marker.exists(), "the checkpoint's pickled object was executed"
    assert_nothing_written(finished, before, rows_before=1)


def test_checkpoint_trained_at_another_resolution(capsys, finished):
    """An encoder checkpoint made for 16x24 frames, found where a 32x48 run looks for its encoder."""
    from mftcn_bench.core.home import BenchHome
    from mftcn_bench.core.specs import parse_override
    from mftcn_bench.run.artifacts import encoder_workdir, prepare_dataset
    from mftcn_bench.run.plan import RunRequest, prepare

    argv = [*TINY_MFTCN, "--set", "task.dataset.height=32", "--set", "task.dataset.width=48"]
    overrides = [parse_override(argv[i + 1]) for i, a in enumerate(argv) if a == "--set"]

    home = BenchHome.resolve(finished)
    prepared = prepare(RunRequest("mftcn1", "cartpole-probe", "smoke", 0, tuple(overrides)))
    dataset = prepare_dataset(prepared, home, show_progress=False)
    workdir = encoder_workdir(prepared, dataset, home)
    workdir.mkdir(parents=True)
    shutil.copy(only(finished, "encoders/mftcn1-*/model.pt"), workdir / "model.pt")
    shutil.copy(only(finished, "encoders/mftcn1-*/fit.json"), workdir / "fit.json")  # marks it finished
    before = snapshot(finished)
    fails(capsys, ["run", *argv, "--home", str(finished)], "was trained on 16x24 (HxW) images, not 32x48",
          "it only embeds 16x24 frames", "--force")
    assert_nothing_written(finished, before, rows_before=1)


# ------------------------------------------------------------------------------------------- training


def test_nan_loss_stops_the_run_at_its_step(capsys, tmp_path):
    line = check_case(capsys, tmp_path, ["run", *TINY_MFTCN, "--set", "encoder.train.lr=1e30",
                                         "--set", "encoder.train.steps=5"],
                      "training loss became nan at step", "no result was written", "lower encoder.train.lr",
                      dataset_ok=True)
    assert int(line.split("at step ")[1].split(";")[0]) >= 1


def test_learning_rate_that_is_not_a_number(capsys, tmp_path):
    check_case(capsys, tmp_path, ["run", *TINY_MFTCN, "--set", "encoder.train.lr=nan"],
               "encoder.train.lr must be a finite number > 0", "got nan", dataset_ok=True)


# ---------------------------------------------------------------------------------------------- plugins


def test_plugin_that_fails_to_import_is_a_warning_and_the_rest_works(capsys, tmp_path, monkeypatch):
    make_plugin(tmp_path, monkeypatch, spec=PLUGIN_SPEC, code=None, name="ghost")
    assert main(["list", "encoders"]) == 0
    captured = capsys.readouterr()
    assert captured.err.strip().splitlines() == [
        line for line in captured.err.strip().splitlines() if line.startswith("mftcn-bench: warning: skipping")]
    assert "'ghost'" in captured.err and "failed to import" in captured.err
    assert "mftcn4" in captured.out and "ghost" not in captured.out
    home = tmp_path / "home"
    assert main(["run", *TINY_TASK, "--encoder", "random-state", "--home", str(home)]) == 0
    assert len(ResultStore(home / "results.sqlite").query()) == 1
    capsys.readouterr()
    check_case(capsys, tmp_path / "b", ["run", *TINY_TASK, "--encoder", "ghost"],
               "encoder 'ghost' cannot be used: package", "failed to import: ModuleNotFoundError")


def test_plugin_whose_class_fails_to_import(capsys, tmp_path, monkeypatch):
    name = make_plugin(tmp_path, monkeypatch, spec=PLUGIN_SPEC, code="raise ImportError('needs libfoo')\n")
    check_case(capsys, tmp_path, ["run", *TINY_TASK, "--encoder", name],
               f"encoder {name!r} failed to import", "ImportError: needs libfoo")


def test_plugin_spec_that_is_not_valid_toml(capsys, tmp_path, monkeypatch):
    name = make_plugin(tmp_path, monkeypatch, spec="family = \n", code="")
    check_case(capsys, tmp_path, ["run", *TINY_TASK, "--encoder", name],
               f"encoder {name!r} cannot be used: spec file", "not valid TOML")


def test_plugin_that_is_not_an_encoder(capsys, tmp_path, monkeypatch):
    name = make_plugin(tmp_path, monkeypatch, spec=PLUGIN_SPEC, code="class Enc:\n    def __init__(self, *a, **k):"
                                                                     "\n        pass\n")
    check_case(capsys, tmp_path, ["run", *TINY_TASK, "--encoder", name],
               "does not implement the Encoder protocol (info, needs_fit, fit, embed, save, load)",
               dataset_ok=True)


@pytest.mark.parametrize("output,message", [
    ("np.zeros((n, dim + 1), np.float32)", "returned embeddings of shape ({n}, 5); expected ({n}, 4)"),
    ("np.zeros((n, dim), np.float64)", "returned embeddings of dtype float64; expected float32"),
    ("np.full((n, dim), np.nan, np.float32)", "returned non-finite embeddings (NaN or inf)"),
    ("None", "returned embeddings of shape NoneType; expected ({n}, 4)"),
], ids=["shape", "dtype", "nan", "none"])
def test_plugin_embeddings_are_checked_at_the_boundary(capsys, tmp_path, monkeypatch, output, message):
    name = make_plugin(tmp_path, monkeypatch, spec=PLUGIN_SPEC, code=PLUGIN_CODE.format(output=output))
    check_case(capsys, tmp_path, ["run", *TINY_TASK, "--encoder", name],
               f"encoder {name!r} " + message.format(n=30), dataset_ok=True)


def test_spec_file_with_code_is_only_data(capsys, tmp_path, monkeypatch):
    """Spec files are TOML parsed as data: Python in a value is a string, Python as the file is an error."""
    marker = tmp_path / "code-ran"
    code = f"__import__('pathlib').Path({str(marker)!r}).touch()"
    name = make_plugin(tmp_path / "a", monkeypatch, spec=PLUGIN_SPEC.replace('"a test plugin"', repr(code)),
                       code=PLUGIN_CODE.format(output="np.zeros((n, dim), np.float32)"), name="data-enc")
    assert main(["list", "encoders"]) == 0
    assert code in capsys.readouterr().out and not marker.exists()
    name = make_plugin(tmp_path / "b", monkeypatch, spec=code + "\n", code="", name="code-enc")
    check_case(capsys, tmp_path, ["run", *TINY_TASK, "--encoder", name], "not valid TOML")
    assert not marker.exists()


# -------------------------------------------------------------------------------------- sweeps, real data


def test_ray_address_that_does_not_answer(tmp_path):
    """In a subprocess: a Ray instance another test left running in this process would be used instead."""
    pytest.importorskip("ray")
    home = tmp_path / "home"
    proc = subprocess.run([sys.executable, "-m", "mftcn_bench.cli", "sweep", "--encoders", "random-state",
                           "--tasks", "cartpole-probe", "--preset", "smoke", "--executor", "ray",
                           "--address", "ray://127.0.0.1:1", "--home", str(home)],
                          capture_output=True, text=True, timeout=120,
                          env={**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parent.parent)})
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and "Traceback" not in proc.stderr and len(lines) == 1, proc.stderr[-2000:]
    assert lines[0].startswith("mftcn-bench: error: Ray cluster at ray://127.0.0.1:1 does not answer (")
    assert "check the address and that the cluster is up" in lines[0]
    assert_nothing_written(home, {})


def test_real_pouring_folder_in_the_wrong_layout(capsys, tmp_path):
    """The Multiview Pouring release unpacked one level too high or only its videos: named, before any work."""
    real = tmp_path / "pouring-release"
    (real / "videos" / "train").mkdir(parents=True)
    (real / "videos" / "train" / "cup_real_view0.mov").write_bytes(b"not read")
    check_case(capsys, tmp_path, ["run", "--encoder", "random-state", "--task", "pouring", "--preset", "smoke",
                                  "--no-progress", "--set", "task.dataset.source=real",
                                  "--set", f"task.dataset.real_path={real}"],
               f"real pouring data in {real}: tfrecords/train/ is missing",
               "expected the Multiview Pouring layout tfrecords/{train,val,test}/ and labels/{val,test}/")


# ---------------------------------------------------------------------------------------------- safe loading

LOADERS_THAT_RUN_CODE = {"pickle.load", "pickle.loads", "marshal.load", "marshal.loads", "eval", "exec",
                         "yaml.load", "yaml.unsafe_load", "dill.load", "joblib.load"}


def unsafe_loads(source: str, origin: str = "<source>") -> list[str]:
    """Calls in Python `source` that could run code or write outside a folder when given a hostile file:
    torch.load without weights_only=True, numpy.load with allow_pickle=True, pickle-like loaders, eval and
    exec, and archive extraction (tarfile/zipfile/shutil) without filter="data"."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if not isinstance(node, ast.Call):
            continue
        name = ast.unparse(node.func)
        keywords = {k.arg: k.value for k in node.keywords}

        def constant(key: str, keywords=keywords):
            value = keywords.get(key)
            return value.value if isinstance(value, ast.Constant) else None

        extracts = name.endswith((".extractall", "unpack_archive")) or (
            name.endswith(".extract") and any(word in name.lower() for word in ("tar", "zip", "archive")))
        if ((name == "torch.load" and constant("weights_only") is not True)
                or (name in ("np.load", "numpy.load") and constant("allow_pickle") is True)
                or name in LOADERS_THAT_RUN_CODE
                or (extracts and constant("filter") != "data")):
            found.append(f"{origin}:{node.lineno}: {ast.unparse(node)}")
    return found


def test_the_unsafe_load_check_finds_what_it_should():
    bad = ("torch.load(p)\ntorch.load(p, weights_only=False)\nnp.load(p, allow_pickle=True)\npickle.loads(b)\n"
           "eval(text)\ntar.extractall(d)\nshutil.unpack_archive(f, d)\nzip_file.extract(m, d)\n")
    assert len(unsafe_loads(bad)) == 8
    good = ("torch.load(p, weights_only=True)\nnp.load(p, allow_pickle=False)\nnp.load(p)\n"
            "tar.extractall(d, filter='data')\nshutil.unpack_archive(f, d, filter='data')\ndf.str.extract(r)\n")
    assert unsafe_loads(good) == []


def test_every_load_in_the_package_is_safe():
    """Checkpoints with weights_only=True, arrays without pickles, no eval, archives only with filter="data"
    (nothing extracts archives today; this keeps it so)."""
    root = Path(__file__).resolve().parent.parent
    files = sorted([*(root / "mftcn_bench").rglob("*.py"), *(root / "examples").rglob("*.py")])
    assert len(files) > 20
    found = [hit for path in files for hit in unsafe_loads(path.read_text(), str(path.relative_to(root)))]
    assert found == []
