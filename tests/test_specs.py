import pytest

from mftcn_bench.core import registry
from mftcn_bench.core.errors import SpecError
from mftcn_bench.core.specs import EncoderSpec, TaskSpec, apply_overrides, parse_override, parse_toml, resolve_config

ENCODER = EncoderSpec("e", "mftcn", "d", 4, 1, 32, {"coords": True}, {"steps": 100, "lr": 0.001})
TASK = TaskSpec("t", "d", "quick", {"dataset": {"episodes": 10, "cameras": ["a"]}, "probe": {"epochs": 5}},
                {"quick": {"task": {"dataset": {"episodes": 4}}, "encoder": {"train": {"steps": 7, "x": 1}}},
                 "paper": {}})


def test_preset_then_overrides():
    preset, config = resolve_config(ENCODER, TASK, None, [("encoder.embedding_dim", 8),
                                                          ("task.probe.epochs", 9)])
    assert preset == "quick"
    assert config["task"]["dataset"]["episodes"] == 4
    assert config["encoder"]["train"]["steps"] == 7
    assert config["encoder"]["embedding_dim"] == 8 and config["task"]["probe"]["epochs"] == 9
    assert resolve_config(ENCODER, TASK, "paper")[1]["task"]["dataset"]["episodes"] == 10


def test_unknown_preset_and_key_suggest_valid_ones():
    with pytest.raises(SpecError, match="did you mean paper"):
        resolve_config(ENCODER, TASK, "papr")
    with pytest.raises(SpecError, match="did you mean encoder.embedding_dim"):
        resolve_config(ENCODER, TASK, None, [("encoder.embeding_dim", 8)])


def test_override_types():
    config = {"a": {"i": 1, "f": 0.5, "b": True, "s": "x", "l": [1]}}
    assert apply_overrides(config, [("a.f", 2)])["a"]["f"] == 2.0
    for key, value in (("a.i", "two"), ("a.i", 1.5), ("a.b", 1), ("a.s", 3), ("a.i", True)):
        with pytest.raises(SpecError, match="expected a"):
            apply_overrides(config, [(key, value)])
    with pytest.raises(SpecError, match="names a table"):
        apply_overrides(config, [("a", 1)])


def test_parse_override_values():
    assert parse_override("encoder.embedding_dim=8") == ("encoder.embedding_dim", 8)
    assert parse_override("task.x=0.5") == ("task.x", 0.5)
    assert parse_override("task.c=fixed") == ("task.c", "fixed")
    assert parse_override("task.l=[1, 2]") == ("task.l", [1, 2])
    with pytest.raises(SpecError, match="KEY=VALUE"):
        parse_override("encoder.embedding_dim")


def test_identity_keys_cannot_be_overridden():
    with pytest.raises(SpecError, match="cannot be changed"):
        resolve_config(ENCODER, TASK, None, [("encoder.family", "x")])


def test_spec_validation():
    with pytest.raises(SpecError, match="unknown keys"):
        EncoderSpec.from_dict("e", {"family": "f", "description": "d", "frams": 2})
    with pytest.raises(SpecError, match="frames must be >= 1"):
        EncoderSpec.from_dict("e", {"family": "f", "description": "d", "frames": 0})
    with pytest.raises(SpecError, match="default_preset"):
        TaskSpec.from_dict("t", {"description": "d", "default_preset": "x", "presets": {"y": {}}})
    with pytest.raises(SpecError, match="not valid TOML"):
        parse_toml("a = ", "x.toml")
    assert EncoderSpec.from_dict("e", {"family": "f", "description": "d", "frames": 5, "stride": 7}).lookback == 29


def test_encoder_defaults_task_wide_then_preset_then_overrides():
    task = TaskSpec.from_dict("t", {
        "description": "d", "default_preset": "quick",
        "encoder_defaults": {"e": {"embedding_dim": 17, "train": {"lr": 0.5}}},
        "presets": {"quick": {"encoder": {"train": {"steps": 7}},
                              "encoder_defaults": {"e": {"train": {"steps": 3}}, "other": {"frames": 2}}},
                    "paper": {}}})
    config = resolve_config(ENCODER, task, "quick")[1]["encoder"]
    assert (config["embedding_dim"], config["train"]["lr"], config["train"]["steps"]) == (17, 0.5, 3)
    assert config["frames"] == 4                        # another encoder's defaults are not applied
    assert resolve_config(ENCODER, task, "paper")[1]["encoder"]["train"]["steps"] == 100
    assert resolve_config(ENCODER, task, "quick", [("encoder.train.steps", 9)])[1]["encoder"]["train"]["steps"] == 9
    with pytest.raises(SpecError, match=r"presets.quick.encoder_defaults.<encoder>\] must be tables"):
        TaskSpec.from_dict("t", {"description": "d", "default_preset": "quick",
                                 "presets": {"quick": {"encoder_defaults": {"e": 3}}}})


@pytest.mark.parametrize("encoder", ["true-state", "random-state"])
def test_state_encoders_take_the_pouring_state_size_from_the_task(encoder):
    from mftcn_bench.data.pouring_labels import STATE_COLUMNS
    from mftcn_bench.run.plan import RunRequest, prepare

    config = prepare(RunRequest(encoder, "pouring", "smoke")).config
    assert config["encoder"]["embedding_dim"] == len(STATE_COLUMNS)


def test_extends_merges_tables_and_a_dataset_reference_is_its_file():
    from mftcn_bench.core.specs import load_spec_tree

    files = {("tasks", "base"): 'description = "b"\ndataset = "d"\n[probe]\nlr = 1\nepochs = 2\n',
             ("tasks", "child"): 'extends = "base"\n[probe]\nlr = 3\n[dataset]\nheight = 9\n',
             ("datasets", "d"): 'name = "d"\nheight = 4\nwidth = 5\n[render]\nshadowsize = 16\n',
             ("tasks", "loop-a"): 'extends = "loop-b"\n', ("tasks", "loop-b"): 'extends = "loop-a"\n'}
    def read(folder, name):
        return files[(folder, name)]

    child = load_spec_tree("tasks", "child", read, "x")
    assert child == {"description": "b", "probe": {"lr": 3, "epochs": 2},
                     "dataset": {"name": "d", "height": 9, "width": 5, "render": {"shadowsize": 16}}}
    with pytest.raises(SpecError, match="extends` loops"):
        load_spec_tree("tasks", "loop-a", read, "x")


def test_same_as_is_the_named_table_with_this_tables_keys_over_it():
    from mftcn_bench.core.specs import load_spec_tree

    files = {("tasks", "control"): '[ppo]\nlr = 1\nframes = 10\n[ppo.net]\nhidden = 4\ndepth = 2\n',
             ("tasks", "expert"): 'extends = "_t"\n[expert_ppo]\nsame_as = "control.ppo"\nframes = 3\n'
                                  '[expert_ppo.net]\ndepth = 1\n',
             ("tasks", "_t"): '[ppo]\nsame_as = "expert_ppo"\nframes = 7\n',
             ("tasks", "self-loop"): '[a]\nsame_as = "b"\n[b]\nsame_as = "a"\n',
             ("tasks", "spec-loop"): '[a]\nsame_as = "spec-loop.a"\n',
             ("tasks", "missing"): '[a]\nsame_as = "control.nothing"\n',
             ("tasks", "bad"): '[a]\nsame_as = "a.b.c"\n'}

    def read(folder, name):
        return files[(folder, name)]

    expert = load_spec_tree("tasks", "expert", read, "x")
    # another spec's table, nested tables merged; a sibling's through a template, itself a reference
    assert expert["expert_ppo"] == {"lr": 1, "frames": 3, "net": {"hidden": 4, "depth": 1}}
    assert expert["ppo"] == {"lr": 1, "frames": 7, "net": {"hidden": 4, "depth": 1}}
    for name, message in (("self-loop", "loops"), ("spec-loop", "loops"), ("bad", "must be"),
                          ("missing", "names no table of spec 'control'; its tables: \\['ppo'\\]")):
        with pytest.raises(SpecError, match=message):
            load_spec_tree("tasks", name, read, "x")


def test_the_experts_ppo_settings_are_the_control_tasks_by_reference():
    """imitate-swingup's expert is swingup's tuned PPO with 1 M frames; cheetah's policy has its expert's
    settings with the paper's 100 test episodes (spec files say so with `same_as`, not with copies)."""
    tables = {name: registry.get("tasks", name).spec.tables for name in ("swingup", "imitate-swingup", "cheetah")}
    assert tables["imitate-swingup"]["expert_ppo"] == {**tables["swingup"]["ppo"], "frames": 1_000_000,
                                                       "eval_episodes": 20}
    assert tables["cheetah"]["ppo"] == {**tables["cheetah"]["expert_ppo"], "eval_episodes": 100}


def test_tasks_share_the_named_dataset():
    from mftcn_bench.core import registry

    tables = {name: registry.get("tasks", name).spec.tables["dataset"]
              for name in ("cartpole-probe", "cartpole-probe-agent-rate", "swingup", "swingup-physics-rate",
                           "swingup-160", "swingup-moving")}
    assert tables["cartpole-probe-agent-rate"] == tables["swingup"] != tables["cartpole-probe"]
    assert tables["cartpole-probe"] == tables["swingup-physics-rate"]
    assert tables["swingup-160"] == tables["swingup-moving"]
    assert {k: v for k, v in tables["swingup-160"].items() if k not in ("height", "width")} == \
        {k: v for k, v in tables["swingup"].items() if k not in ("height", "width")}


def test_probe_state_readout_is_the_cartpole_probe():
    """swingup-probe-state's [probe] table is cartpole-probe's, preset by preset (one probe, two uses)."""
    probe_spec = registry.get("tasks", "cartpole-probe").spec
    readout_spec = registry.get("tasks", "swingup-probe-state").spec
    encoder = registry.get("encoders", "mftcn5").spec
    for preset in ("quick", "paper"):
        _, probe = resolve_config(encoder, probe_spec, preset, [])
        _, readout = resolve_config(encoder, readout_spec, preset, [])
        assert readout["task"]["probe"] == probe["task"]["probe"], preset
        assert readout["task"]["env"]["embedding_difference"] is True
