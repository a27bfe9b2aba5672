"""The example third-party package installs beside mftcn-bench and runs through the CLI."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow
EXAMPLE = Path(__file__).resolve().parent.parent / "examples" / "mftcn-bench-example-encoder"


def test_example_plugin_registers_and_runs(tmp_path):
    target = tmp_path / "site"
    subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--no-build-isolation",
                    "--target", str(target), str(EXAMPLE)], check=True, capture_output=True, timeout=300)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(target), os.environ.get("PYTHONPATH", "")]),
           "MFTCN_BENCH_HOME": str(tmp_path / "home")}

    def cli(*args):
        return subprocess.run([sys.executable, "-m", "mftcn_bench.cli", *args], capture_output=True,
                              text=True, env=env, timeout=600)

    listing = cli("list", "encoders")
    assert listing.returncode == 0 and "pixel-pca" in listing.stdout and "Example plugin" in listing.stdout
    check = cli("check", "encoder", "pixel-pca")
    assert check.returncode == 0, check.stdout[-2000:] + check.stderr[-2000:]
    assert "keeps the encoder contract" in check.stdout and "ok    embed_episode" in check.stdout
    run = cli("run", "--encoder", "pixel-pca", "--task", "cartpole-probe", "--preset", "smoke", "--no-progress")
    assert run.returncode == 0, run.stderr[-2000:]
    assert "pixel-pca on cartpole-probe" in run.stdout and "| Average" in run.stdout
