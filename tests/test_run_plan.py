"""The runner's plan (`PreparedRun`): what a run needs, learnt once; `--force` and concurrent runs of one id."""

from __future__ import annotations

import threading
import time

import pytest

from mftcn_bench.encoders.base import Encoder
from mftcn_bench.run import artifacts, plan, runner
from mftcn_bench.run.plan import RunRequest, prepare, prepare_with_encoder
from mftcn_bench.run.runner import run
from tests.test_identity import TINY

FIT = (*TINY, ("encoder.train.steps", 4), ("encoder.train.checkpoint_every", 2), ("encoder.train.episode_pool", 2),
       ("encoder.train.batch_timesteps", 4))


@pytest.mark.parametrize(("encoder", "task", "reads"), [
    ("true-state", "swingup", False), ("random-state", "swingup", False), ("lite0-features", "swingup", False),
    ("pixels-cnn", "swingup", False), ("true-state", "cheetah", False),
    ("mftcn1", "swingup", True),               # its fit reads the data
    ("true-state", "swingup-probe-state", True),  # the task fits its probe on the data
    ("true-state", "cartpole-probe", True),
])
def test_the_plan_says_whether_a_run_reads_data(encoder, task, reads):
    assert prepare(RunRequest(encoder, task, "smoke")).reads_data is reads


def test_the_difference_variant_of_cheetah_shares_its_expert_data_and_fit_and_is_another_run():
    """cheetah-difference changes only how the policy reads the embedding: the expert (on state), its
    demonstrations and the encoder fit are cheetah's own; the run is not."""
    plain, difference = (prepare(RunRequest("mftcn5", task, "paper", 0)) for task in ("cheetah", "cheetah-difference"))
    assert difference.task.env_config.embedding_difference and not plain.task.env_config.embedding_difference
    assert difference.dataset_key == plain.dataset_key
    assert plan.encoder_key_of(difference, "data") == plan.encoder_key_of(plain, "data")
    assert plan.run_id_of(difference, "data") != plan.run_id_of(plain, "data")


def test_an_encoder_that_fits_nothing_collects_nothing_on_a_control_task(home):
    """true-state on swing-up and on cheetah: no dataset collected, no cheetah expert trained."""
    for task in ("swingup", "cheetah"):
        outcome = run(RunRequest("true-state", task, "smoke"), home, show_progress=False)
        assert outcome.record.dataset_id is None and outcome.record.config["dataset_path"] is None
    assert not [p for p in home.datasets.glob("*") if not p.name.startswith(".")]
    assert not list(home.experts.glob("*")) if home.experts.exists() else True
    again = run(RunRequest("true-state", "swingup", "smoke"), home, show_progress=False)
    assert again.reused, "a data-free run is found again by its id"


def test_the_plan_constructs_the_encoder_once_per_run(home, monkeypatch):
    built: list[str] = []
    construct = plan.construct_encoder

    def counting(entry, *args, **kwargs):
        built.append(entry.name)
        return construct(entry, *args, **kwargs)

    for module in (plan, artifacts):  # the plan constructs it; a build without it would construct another
        monkeypatch.setattr(module, "construct_encoder", counting)
    run(RunRequest("lite0-features", "cartpole-probe", "smoke", 0, TINY), home, show_progress=False)
    assert built == ["lite0-features"]


def test_the_plan_holds_no_encoder_and_hands_its_own_to_the_build(home):
    """The plan is data (a sweep keeps many, not their weights); the encoder constructed to plan the run
    comes back beside it, and the build uses that one rather than constructing another."""
    request = RunRequest("true-state", "swingup", "smoke")
    prepared, untrained = prepare_with_encoder(request)
    assert isinstance(untrained, Encoder)
    assert not [name for name, value in vars(prepared).items() if isinstance(value, Encoder)]
    assert plan.run_id_of(prepared, None) == plan.run_id_of(prepare(request), None)  # one plan either way
    encoder, fit = artifacts.build_encoder(prepared, None, home, show_progress=False, untrained=untrained)
    assert encoder is untrained and fit == {"fitted": False, "reused": False, "device": "cpu"}
    other, _ = artifacts.build_encoder(prepared, None, home, show_progress=False)
    assert other is not untrained


@pytest.mark.slow
def test_force_fits_again_in_the_runs_folder_and_leaves_the_shared_checkpoint(home):
    first = run(RunRequest("mftcn1", "cartpole-probe", "smoke", 0, FIT), home, show_progress=False).record
    shared = home.encoders.glob("mftcn1-*/model.pt")
    (checkpoint,) = shared
    before = (checkpoint.read_bytes(), checkpoint.stat().st_mtime_ns)
    forced = run(RunRequest("mftcn1", "cartpole-probe", "smoke", 0, FIT, force=True), home, show_progress=False)
    assert (checkpoint.read_bytes(), checkpoint.stat().st_mtime_ns) == before, "the shared checkpoint is untouched"
    if forced.record.run_id == first.run_id:  # reproduced: the stored record stays, the forced folder is gone
        assert "the same metrics" in forced.notes[-1] and not (home.runs / f".{first.run_id}.rerun").exists()
    else:  # another result: its own record, its own fit beside it
        fit = forced.record.config["fit"]
        assert fit["fitted"] is True and fit["checkpoint"].startswith(str(home.runs / forced.record.run_id))
    later = run(RunRequest("mftcn1", "cartpole-probe", "smoke", 1, FIT), home, show_progress=False).record
    assert later.config["fit"]["fitted"] is True  # another seed: another key, fitted once
    assert run(RunRequest("mftcn1", "cartpole-probe", "smoke", 0, FIT), home, show_progress=False).reused


def test_two_requests_for_one_run_compute_it_once(home, monkeypatch):
    """Two runs of one id at once (two shells, or a sweep beside a run): the second waits on the run's lock,
    then finds the first's result; `runs/<id>` is never written by both."""
    from mftcn_bench.tasks.probe import CartpoleProbe

    evaluations: list[float] = []
    evaluate = CartpoleProbe.evaluate

    def slow(self, encoder, dataset, workdir):
        evaluations.append(time.monotonic())
        time.sleep(0.5)  # long enough for the other thread to arrive while this one holds the run
        return evaluate(self, encoder, dataset, workdir)

    monkeypatch.setattr(CartpoleProbe, "evaluate", slow)
    request = RunRequest("true-state", "cartpole-probe", "smoke", 0, TINY)
    run(RunRequest("true-state", "cartpole-probe", "smoke", 1, TINY), home, show_progress=False)  # data in place
    evaluations.clear()
    outcomes: list[runner.RunOutcome] = []
    threads = [threading.Thread(target=lambda: outcomes.append(run(request, home, show_progress=False)))
               for _ in range(2)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=120)
    assert len(evaluations) == 1 and len(outcomes) == 2
    assert sorted(o.reused for o in outcomes) == [False, True]
    assert outcomes[0].record.run_id == outcomes[1].record.run_id
