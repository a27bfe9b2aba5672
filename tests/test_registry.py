import sys

import pytest

from mftcn_bench import registry
from mftcn_bench.errors import SpecError


def test_builtins_are_registered_with_specs():
    encoders = registry.entries("encoders")
    for name in ("mftcn1", "mftcn2", "mftcn4", "mftcn5"):
        assert name in encoders and encoders[name].description
    assert encoders["mftcn4"].spec.lookback == 4
    assert "cartpole-probe" in registry.entries("tasks")


def test_unknown_name_suggests():
    with pytest.raises(SpecError, match=r"unknown encoder .mftcn3.; did you mean .*mftcn\d.* valid: .*mftcn1"):
        registry.get("encoders", "mftcn3")


def test_broken_plugin_is_a_warning_and_the_rest_works(tmp_path, monkeypatch):
    dist = tmp_path / "broken_plugin-1.0.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: broken-plugin\nVersion: 1.0\n")
    (dist / "entry_points.txt").write_text("[mftcn_bench.encoders]\nbroken = no_such_module_xyz:Enc\n")
    monkeypatch.setattr(sys, "path", [str(tmp_path), *sys.path])
    with pytest.warns(registry.PluginWarning, match="broken"):
        found = registry.entries("encoders")
    assert "broken" not in found and "mftcn4" in found


def test_list_reports_an_entry_point_that_names_a_missing_class(tmp_path, monkeypatch, capsys):
    from mftcn_bench.cli import main
    from tests.plugins import install

    install(monkeypatch, tmp_path, "missingcls", "0.3", {"enc": "class Something:\n    pass\n"},
            {"no-such-class": "enc:NotThere"})
    assert main(["list", "encoders"]) == 0
    out = capsys.readouterr()
    assert "no-such-class" not in out.out and "mftcn4" in out.out and "mftcn-bench 0.1.0" in out.out
    assert "skipping encoder 'no-such-class'" in out.err and "NotThere" in out.err
