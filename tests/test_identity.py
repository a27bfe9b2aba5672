"""Identities follow the code: a plugin's source or version, a collector's modules, and `--force`."""

from __future__ import annotations

import numpy as np
import pytest

from mftcn_bench.core import identity
from mftcn_bench.results.selection import code_label
from mftcn_bench.results.store import ResultStore
from mftcn_bench.run.plan import RunRequest, encoder_key_of, prepare, run_id_of
from mftcn_bench.run.runner import run
from tests.plugins import install

ENCODER = "from mftcn_bench.encoders.baselines import TrueStateEncoder\n\n\nclass PlugEncoder(TrueStateEncoder):\n" \
          "    pass\n"
TINY = (("task.dataset.episode_length", 30), ("task.dataset.train_episodes", 3), ("task.dataset.test_episodes", 1),
        ("task.dataset.height", 16), ("task.dataset.width", 24), ("task.probe.epochs", 3),
        ("task.probe.hidden", [8]), ("task.probe.batch_size", 16))


def _ids(name: str) -> tuple[str, str]:
    prepared = prepare(RunRequest(name, "cartpole-probe", "smoke"))
    return run_id_of(prepared, "same-data"), encoder_key_of(prepared, "same-data")


def test_a_plugins_source_and_version_key_its_runs(tmp_path, monkeypatch):
    plugin = install(monkeypatch, tmp_path, "idplug_a", "1.0", {"enc": ENCODER}, {"plug-state": "enc:PlugEncoder"})
    first = _ids("plug-state")
    assert _ids("plug-state") == first, "the same code and config give the same ids"
    plugin.edit("enc", ENCODER + "    needs_fit = False\n")
    edited = _ids("plug-state")
    assert edited[0] != first[0] and edited[1] != first[1]
    plugin.set_version("1.1")
    bumped = _ids("plug-state")
    assert bumped[0] not in (first[0], edited[0]) and bumped[1] != edited[1]
    code = prepare(RunRequest("plug-state", "cartpole-probe", "smoke")).code.encoder
    assert (code.distribution, code.version, code.is_plugin) == ("idplug_a", "1.1", True)


def test_a_plugins_helper_module_keys_it_through_imports(tmp_path, monkeypatch):
    """The closure follows the plugin's own imports (and into the harness), not only the entry module."""
    modules = {"helper": "SCALE = 1\n",
               "enc": "from idplug_b.helper import SCALE\n" + ENCODER}
    plugin = install(monkeypatch, tmp_path, "idplug_b", "1.0", modules, {"plug-b": "enc:PlugEncoder"})
    before = identity.code_identity("idplug_b.enc")
    closure = [m for m, _ in identity._closure(("idplug_b.enc",), frozenset({"idplug_b", "mftcn_bench"}))]
    assert "idplug_b.helper" in closure and "mftcn_bench.encoders.baselines" in closure
    plugin.edit("helper", "SCALE = 2\n")
    assert identity.code_identity("idplug_b.enc").source != before.source


def test_dataset_ids_follow_the_collectors_code(tmp_path, monkeypatch):
    """A dataset's id covers every module its collector imports: the cartpole collector's rendering code,
    and for a plugin's collector its helpers."""
    harness = [m for m, _ in identity._closure(("mftcn_bench.data.cartpole",), frozenset({"mftcn_bench"}))]
    assert "mftcn_bench.sim.rendering" in harness
    assert "mftcn_bench.rl.ppo" not in harness, "a change to PPO does not re-collect cartpole's data"
    modules = {"pixels": "VALUE = 1\n",
               "collect": "from idplug_c import pixels\n\n\ndef collect(config, index):\n    return pixels.VALUE\n"}
    plugin = install(monkeypatch, tmp_path, "idplug_c", "1.0", modules, {})
    from mftcn_bench.data.dataset import dataset_id

    def collector_id() -> str:
        import importlib

        return dataset_id({"name": "x", "seed": 0}, importlib.import_module("idplug_c.collect").collect)

    first = collector_id()
    assert collector_id() == first
    plugin.edit("pixels", "VALUE = 2\n")
    assert collector_id() != first


def test_dataset_ids_follow_the_code_not_its_layout(tmp_path, monkeypatch):
    """A comment, a docstring and a blank line added to a collector's module leave its datasets' id as it
    was; a changed constant re-keys them."""
    code = "SCALE = 1\n\n\ndef collect(config, index):\n    return SCALE * index\n"
    plugin = install(monkeypatch, tmp_path, "idplug_d", "1.0", {"collect": code}, {})
    from mftcn_bench.data.dataset import dataset_id

    def collector_id() -> str:
        import importlib

        return dataset_id({"name": "x", "seed": 0}, importlib.import_module("idplug_d.collect").collect)

    first = collector_id()
    laid_out = ('"""Collects x."""\n\n# the scale of every frame\nSCALE = 1  # why: none\n\n\n\n'
                'def collect(config, index):\n    """One frame."""\n\n    return SCALE * index\n')
    plugin.edit("collect", laid_out)
    assert collector_id() == first, "comments, docstrings and blank lines are not the code's meaning"
    plugin.edit("collect", laid_out.replace("SCALE = 1", "SCALE = 2"))
    assert collector_id() != first
    plugin.edit("collect", laid_out.replace("return SCALE * index", "return SCALE + index"))
    assert collector_id() != first


def test_the_normal_form_drops_only_docstrings(tmp_path):
    """Only the first string statement of a module, class or function body is a docstring: a string
    value, or a string statement after the first, is code."""
    module = tmp_path / "m.py"

    def form(text: str) -> bytes:
        module.write_text(text)
        return identity.normal_form(module)

    plain = form('X = "a"\n\n\nclass C:\n    def f(self):\n        return 1\n')
    assert form('"""M."""\nX = "a"  # a\n\n\nclass C:\n    """C."""\n\n    def f(self):\n'
                '        """f."""\n        return 1\n') == plain
    assert form('X = "b"\n\n\nclass C:\n    def f(self):\n        return 1\n') != plain
    assert form('X = "a"\n"""a statement after the first"""\n\n\nclass C:\n    def f(self):\n'
                '        return 1\n') != plain


def test_a_base_weights_file_replaced_at_the_same_path_keys_new_runs(tmp_path):
    """The config names a weights file by its path; the run id and the encoder key hold its checksum, so
    other weights at that path are never served the stored result of the old ones."""
    from tests.test_inception import perturbed_module, torchvision_file

    path = torchvision_file(tmp_path, perturbed_module(seed=0))

    def prepared():
        return prepare(RunRequest("inception", "pouring", "smoke", 0,
                                  (("encoder.model.base.weights", str(path)), ("encoder.model.base.input_size", 75))))

    first = prepared()
    assert first.base is not None and len(first.base["weights_sha256"]) == 64
    assert run_id_of(prepared(), "fp") == run_id_of(first, "fp")
    torchvision_file(tmp_path, perturbed_module(seed=1))  # the same file name, other weights
    replaced = prepared()
    assert replaced.config == first.config and replaced.base != first.base
    assert run_id_of(replaced, "fp") != run_id_of(first, "fp")
    assert encoder_key_of(replaced, "fp") != encoder_key_of(first, "fp")


def test_run_ids_do_not_follow_the_report_layer():
    """The runner draws each run's curve (`results.figure`) but its closure, which keys every run, holds
    none of the report's modules: editing a paper table or a board re-keys no run."""
    runner = {m for m, _ in identity._closure(("mftcn_bench.run.runner",), frozenset({"mftcn_bench"}))}
    assert "mftcn_bench.results.figure" in runner and "mftcn_bench.results.store" in runner
    report = {"mftcn_bench.results.paper_tables", "mftcn_bench.results.plots", "mftcn_bench.results.report",
              "mftcn_bench.results.selection", "mftcn_bench.results.leaderboard"}
    assert not runner & report, sorted(runner & report)


def test_code_identity_does_not_hash_how_it_is_installed():
    code = identity.code_identity("mftcn_bench.encoders.mftcn")
    assert "editable" not in code.key() and code.distribution == "mftcn-bench"
    assert identity.code_identity("mftcn_bench.encoders.mftcn") == code


@pytest.mark.slow
def test_force_never_leaves_two_results_under_one_id(home, monkeypatch):
    from mftcn_bench.tasks.probe import CartpoleProbe as ProbeTask

    request = RunRequest("true-state", "cartpole-probe", "smoke", 0, TINY)
    first = run(request, home, show_progress=False).record
    forced = RunRequest("true-state", "cartpole-probe", "smoke", 0, TINY, force=True)
    again = run(forced, home, show_progress=False)
    assert again.record.run_id == first.run_id and again.record.metrics == first.metrics
    assert "the same metrics" in again.notes[-1]

    evaluate = ProbeTask.evaluate

    def shifted(self, encoder, dataset, workdir=None):  # a nondeterministic evaluation
        result = evaluate(self, encoder, dataset, workdir)
        result.metrics["average"] = float(np.float64(result.metrics["average"]) + 1.0)
        return result

    monkeypatch.setattr(ProbeTask, "evaluate", shifted)
    with pytest.warns(UserWarning, match="gave other metrics"):
        other = run(forced, home, show_progress=False).record
    assert other.run_id != first.run_id and other.config["rerun_of"] == first.run_id
    stored = {r.run_id: r for r in ResultStore(home.database).query()}
    assert set(stored) == {first.run_id, other.run_id}
    assert stored[first.run_id].metrics == first.metrics, "the first result stays under its id"
    assert (home.runs / other.run_id / "result.json").exists() and (home.runs / first.run_id / "result.json").exists()
    assert first.created_at and code_label(first) == "mftcn-bench " + first.config["code"]["encoder"]["version"]
