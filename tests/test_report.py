import copy

from mftcn_bench import registry
from mftcn_bench.report import matches_current_specs
from mftcn_bench.specs import resolve_config
from mftcn_bench.store import RunRecord


def record(config, encoder="mftcn4"):
    return RunRecord("id", encoder, "cartpole-probe", "smoke", 0, "d", config, {}, {}, {})


def test_only_runs_of_the_current_specs_are_tabled():
    _, config = resolve_config(registry.get("encoders", "mftcn4").spec,
                               registry.get("tasks", "cartpole-probe").spec, "smoke",
                               [("encoder.embedding_dim", 8)])
    assert matches_current_specs(record(config))
    stale = copy.deepcopy(config)
    stale["encoder"]["train"]["lr"] = 0.5
    assert not matches_current_specs(record(stale))
    other_task = copy.deepcopy(config)
    other_task["task"]["probe"]["epochs"] += 1
    assert not matches_current_specs(record(other_task))
    assert not matches_current_specs(record(config, encoder="uninstalled-plugin"))
