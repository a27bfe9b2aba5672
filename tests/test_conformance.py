"""`mftcn-bench check encoder`: passes on built-ins, names the broken part of a broken plugin, exit 2."""

from __future__ import annotations

import pytest

from mftcn_bench.cli import main
from tests.plugins import TRUE_STATE_SPEC, install

BROKEN = '''
import numpy as np

from mftcn_bench.encoders.baselines import TrueStateEncoder


class EpisodeOffByOne(TrueStateEncoder):
    """embed_episode shifts every embedding one frame late: the bug `embed` vs `embed_episode` catches."""

    def embed_episode(self, frames, state=None):
        out = self.embed_episode_exact(state)
        return np.concatenate([out[:1], out[:-1]])

    def embed_episode_exact(self, state):
        from mftcn_bench.encoders.baselines import state_embedding

        return state_embedding(np.asarray(state, dtype=np.float64)).astype(np.float32)


class WrongDtype(TrueStateEncoder):
    def embed(self, clips):
        return super().embed(clips).astype(np.float64)


class ForgetsOnLoad(TrueStateEncoder):
    """A checkpoint that does not restore what it embeds with."""

    def __init__(self, spec, image_shape, seed):
        super().__init__(spec, image_shape, seed)
        self.offset = 0.0

    def save(self, path):
        self.offset = 1.0  # saving changes the live encoder, the file keeps nothing
        path.write_bytes(b"")

    def load(self, path):
        self.offset = 0.0

    def embed(self, clips):
        return super().embed(clips) + np.float32(self.offset)


class Fitted(TrueStateEncoder):
    """A true-state encoder with a fit: `count` is added to every embedding."""

    needs_fit = True

    def __init__(self, spec, image_shape, seed):
        super().__init__(spec, image_shape, seed)
        self.count = 0.0

    def embed_state(self, state):  # what `embed` and the rollouts' `push` both go through
        return super().embed_state(state) + np.float32(self.count)


class PeeksAtTest(Fitted):
    """Its fit reads the test episodes: what it learns depends on them."""

    def fit(self, dataset, budget, progress, workdir):
        self.count = float(sum(episode.state.mean() for episode in dataset.iter_episodes("test")))
        return {}


class ForgetsOnResume(Fitted):
    """Checkpoints its step but not what it learnt: a restarted fit counts only the steps after the checkpoint."""

    def fit(self, dataset, budget, progress, workdir):
        workdir.mkdir(parents=True, exist_ok=True)
        checkpoint = workdir / "step.txt"
        start = int(checkpoint.read_text()) if checkpoint.exists() else 0
        for step in range(start + 1, budget.steps + 1):
            checkpoint.write_text(str(step))
            self.count += 1.0
            progress(step, budget.steps, {})
        return {"steps": float(budget.steps)}


class ProbeShapedOnly(TrueStateEncoder):
    """Written against the probe's 48x96 frames: it passes every check made at that shape."""

    def embed(self, clips):
        assert clips.frames.shape[2:4] == (48, 96), "expects 48x96 frames"
        return super().embed(clips)
'''


def _check(capsys, name: str) -> tuple[int, list[str]]:
    code = main(["check", "encoder", name])
    out = capsys.readouterr()
    return code, out.out.splitlines() + out.err.splitlines()


@pytest.mark.parametrize("name", ["true-state", "random-state", "lite0-features"])
def test_builtins_keep_the_contract(capsys, name):
    code, lines = _check(capsys, name)
    assert code == 0, lines
    checks = {line.split()[1]: line.split()[0] for line in lines if line[:4] in ("ok  ", "FAIL", "skip")}
    assert set(checks) == {"spec", "construct", "privileged", "metadata", "fit", "embed", "embed_episode", "streaming",
                           "determinism", "train-only", "resume", "save-load", "device",
                           "shapes"} and set(checks.values()) == {"ok"}


@pytest.mark.slow
def test_a_time_contrastive_builtin_keeps_the_contract(capsys):
    code, lines = _check(capsys, "mftcn2")
    assert code == 0, lines


@pytest.mark.parametrize(("name", "failing"), [("off-by-one", "embed_episode"), ("wrong-dtype", "embed"),
                                               ("peeks", "train-only"), ("forgets-resume", "resume"),
                                               ("forgets", "save-load"), ("probe-shaped", "shapes")])
def test_a_broken_plugin_fails_the_check_that_finds_it(capsys, tmp_path, monkeypatch, name, failing):
    install(monkeypatch, tmp_path, "brokenplug", "0.1", {"enc": BROKEN},
            {"off-by-one": "enc:EpisodeOffByOne", "wrong-dtype": "enc:WrongDtype", "forgets": "enc:ForgetsOnLoad",
             "probe-shaped": "enc:ProbeShapedOnly", "peeks": "enc:PeeksAtTest",
             "forgets-resume": "enc:ForgetsOnResume"},
            spec=TRUE_STATE_SPEC.replace("steps = 0", "steps = 4"))
    code, lines = _check(capsys, name)
    assert code == 2
    failed = [line for line in lines if line.startswith("FAIL")]
    assert failed and failed[0].split()[1] == failing, lines
    assert lines[-1].startswith("mftcn-bench: error: encoder") and "failed" in lines[-1]


def test_an_unknown_encoder_is_one_line(capsys):
    code, lines = _check(capsys, "mftcn3")
    assert code == 2 and len(lines) == 1 and "did you mean" in lines[0]
