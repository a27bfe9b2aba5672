"""Privileged inputs: an encoder reads the true state or actions only when it declares them."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mftcn_bench.cli import main
from mftcn_bench.core import registry
from mftcn_bench.core.errors import BenchError
from mftcn_bench.data.dataset import ensure_dataset
from mftcn_bench.data.synthetic import synthetic_collector
from mftcn_bench.encoders.base import ClipBatch, embed_clips_of_episode
from mftcn_bench.encoders.privileged import (
    PrivilegedInputError,
    Withheld,
    dataset_for,
    declared_inputs,
    is_reference,
)
from mftcn_bench.results.leaderboard import render_boards
from mftcn_bench.results.store import ResultStore
from mftcn_bench.rl.observers import make_observer
from mftcn_bench.run.construct import construct_encoder
from tests.plugins import install

RANDOM_STATE_SPEC = (Path(__file__).resolve().parent.parent / "encoders" / "random-state.toml").read_text()

# A pixel encoder that reads the true state instead (what a plugin could do to top a board), and the same
# encoder declaring it.
LEAKY = '''
import numpy as np
from mftcn_bench.encoders.baselines import RandomStateEncoder


class Leaky(RandomStateEncoder):
    def embed(self, clips):
        state = np.asarray(clips.state)[:, -1]
        out = np.zeros((len(state), self.spec.embedding_dim), np.float32)
        out[:, :state.shape[1]] = state[:, :self.spec.embedding_dim]
        return out


class Declared(Leaky):
    privileged_inputs = ("state",)
'''

TINY = ["--task", "cartpole-probe", "--preset", "smoke", "--no-progress",
        "--set", "task.dataset.episode_length=30", "--set", "task.dataset.train_episodes=3",
        "--set", "task.dataset.test_episodes=1", "--set", "task.dataset.height=16",
        "--set", "task.dataset.width=24", "--set", "task.probe.epochs=3", "--set", "task.probe.hidden=[8]",
        "--set", "task.probe.batch_size=16"]


@pytest.fixture
def leaky(tmp_path, monkeypatch):
    monkeypatch.setattr("mftcn_bench.tasks.probe.collect_episode", synthetic_collector)
    return install(monkeypatch, tmp_path / "plugin", "leaky_plugin", "0.1.0", {"leak": LEAKY},
                   {"leaky": "leak:Leaky", "leaky-declared": "leak:Declared"}, spec=RANDOM_STATE_SPEC)


def test_an_undeclared_read_of_the_state_is_one_line_exit_2_and_nothing_stored(leaky, home, capsys):
    assert main(["run", "--encoder", "leaky", *TINY]) == 2
    lines = [line for line in capsys.readouterr().err.splitlines() if "warning:" not in line]
    assert len(lines) == 1
    err = lines[0]
    assert "encoder 'leaky' read the true state" in err and 'privileged_inputs = ("state",)' in err
    assert ResultStore(home.database).query() == []


def test_a_declared_read_runs_and_its_record_and_board_say_so(leaky, home, tmp_path, capsys):
    assert main(["run", "--encoder", "leaky-declared", *TINY]) == 0
    (record,) = ResultStore(home.database).query()
    assert record.config["privileged"] == ["state"]
    board = render_boards([record], accept=lambda r: True)["cartpole-probe.md"]  # its overrides count here
    references = board[board.index("References"):]
    assert "leaky-declared" in references and "reads: state" in references


def test_withheld_refuses_every_use():
    withheld = Withheld("state", "mine")
    for use in (lambda w: w[:, -1], np.asarray, len, lambda w: w.shape, lambda w: w + 1, bool,
                lambda w: np.concatenate([w, w])):
        with pytest.raises(PrivilegedInputError, match="encoder 'mine' read the true state"):
            use(withheld)
    import copy
    import pickle

    assert repr(copy.deepcopy(withheld)) == repr(pickle.loads(pickle.dumps(withheld))) == "Withheld('state')"


def test_declarations_of_the_builtins():
    def declared(name):
        return declared_inputs(registry.get("encoders", name).load())

    assert declared("true-state") == declared("true-state-noisy") == ("state",)
    assert declared("pve") == ("action",)
    for name in ("mftcn5", "tcn", "pixels-cnn", "random-state", "lite0-features", "shuffle-and-learn"):
        assert declared(name) == ()
    assert is_reference(("state",)) and not is_reference(("action",)) and not is_reference(())


def test_an_unknown_declaration_is_refused():
    class Odd:
        privileged_inputs = ("reward",)

    with pytest.raises(BenchError, match=r"declares privileged_inputs \['reward'\]; allowed"):
        declared_inputs(Odd())


def test_fit_data_and_every_embedding_path_withhold_what_is_not_declared(tmp_path):
    config = {"name": "t", "pattern": "gradient", "cameras": ["a"], "height": 8, "width": 8, "episode_length": 6,
              "train_episodes": 1, "test_episodes": 1, "seed": 0}
    dataset = ensure_dataset(tmp_path, config, synthetic_collector, show_progress=False)
    pixels = construct_encoder(registry.get("encoders", "random-state"), _config("random-state"), 0, (8, 8))
    truth = construct_encoder(registry.get("encoders", "true-state"), _config("true-state"), 0, (8, 8))
    pve = construct_encoder(registry.get("encoders", "pve"), _config("pve"), 0, (8, 8))
    episode = dataset.load(0)

    seen = dataset_for(pixels, dataset).load(0)
    assert isinstance(seen.state, Withheld) and isinstance(seen.action, Withheld)
    np.testing.assert_array_equal(seen.frames, episode.frames)
    by_pve = dataset_for(pve, dataset).load(0)
    assert isinstance(by_pve.state, Withheld) and np.array_equal(by_pve.action, episode.action)
    assert np.array_equal(dataset_for(truth, dataset).load(0).state, episode.state)

    received = []

    class Spy(type(pixels)):  # records what reaches `embed`
        def embed(self, clips: ClipBatch) -> np.ndarray:
            received.append(clips.state)
            return super().embed(clips)

    spy = Spy(pixels.spec, image_shape=(8, 8), seed=0)
    embed_clips_of_episode(spy, episode.frames[0], episode.state)
    observer = make_observer(truth, 1)
    out = observer.push(None, np.ones(1, bool), episode.state[:1])
    assert out.shape == (1, truth.info.embedding_dim)  # the declared encoder gets the state
    assert received and all(isinstance(s, Withheld) for s in received)


def _config(name: str) -> dict:
    from mftcn_bench.core.specs import resolve_config

    entry = registry.get("encoders", name)
    return resolve_config(entry.spec, registry.get("tasks", "cartpole-probe").spec, "smoke")[1]["encoder"]
