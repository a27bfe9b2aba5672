import sys

import pytest

from mftcn_bench.core import registry
from mftcn_bench.core.errors import SpecError


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


def test_a_family_entry_point_serves_every_spec_of_its_family(tmp_path, monkeypatch):
    """One entry point `<family>.family`; variants are spec files (a template `_name.toml` is not one), and a
    new spec file is a new variant without reinstalling anything."""
    from tests.plugins import install

    plugin = install(monkeypatch, tmp_path, "famplug", "1.0", {"enc": "from mftcn_bench.encoders.baselines import "
                     "TrueStateEncoder as Enc\n"}, {"fam.family": "enc:Enc"})
    folder = tmp_path / "famplug" / "specs" / "encoders"
    (folder / "fam.family.toml").unlink()  # the helper writes one spec per entry point; a family has none
    (folder / "_base.toml").write_text('family = "fam"\ndescription = "base"\nembedding_dim = 5\n[train]\nsteps = 0\n')
    (folder / "fam-a.toml").write_text('extends = "_base"\ndescription = "variant a"\n')
    (folder / "other.toml").write_text('family = "not-fam"\ndescription = "x"\n')
    found = registry.entries("encoders")
    assert "fam-a" in found and "_base" not in found and "other" not in found and "fam.family" not in found
    assert found["fam-a"].spec.description == "variant a" and found["fam-a"].spec.embedding_dim == 5
    assert found["fam-a"].entry_point.value == "famplug.enc:Enc"
    (folder / "fam-b.toml").write_text('extends = "fam-a"\ndescription = "variant b"\nframes = 2\n')
    assert registry.get("encoders", "fam-b").spec.frames == 2
    assert plugin.dist.exists()


def test_the_mftcn_variants_are_spec_files_of_one_family():
    encoders = registry.entries("encoders")
    mftcn = sorted(name for name, e in encoders.items() if e.spec.family == "mftcn")
    assert mftcn == ["mftcn1", "mftcn13", "mftcn2", "mftcn29", "mftcn4", "mftcn5", "mftcn7"]
    assert {encoders[n].registered_by.name for n in mftcn} == {"mftcn.family"}
    assert encoders["mftcn29"].spec.lookback == 29 and encoders["mftcn29"].spec.model["base"]["layer"] == 10


def test_a_plugin_in_a_namespace_package_keeps_its_specs_beside_its_code(tmp_path, monkeypatch):
    """`acme` is a namespace package (no `__init__.py`) shared by several distributions; the plugin's
    code and specs sit in `acme.vision`: the registry finds `acme/vision/specs/encoders/<name>.toml`,
    nearest first, without importing the encoder's module."""
    import importlib

    from mftcn_bench.core import identity
    from tests.plugins import TRUE_STATE_SPEC

    package = tmp_path / "acme" / "vision"
    (package / "specs" / "encoders").mkdir(parents=True)
    (package / "__init__.py").write_text("")
    (package / "enc.py").write_text("raise ImportError('imported while resolving specs')\n")
    (package / "specs" / "encoders" / "acme-enc.toml").write_text(
        TRUE_STATE_SPEC.replace('description = "', 'description = "acme: ', 1))
    dist = tmp_path / "acme_vision-1.0.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: acme-vision\nVersion: 1.0\n")
    (dist / "entry_points.txt").write_text("[mftcn_bench.encoders]\nacme-enc = acme.vision.enc:Enc\n")
    monkeypatch.setattr(sys, "path", [str(tmp_path), *sys.path])
    identity._package_root.cache_clear()
    importlib.invalidate_caches()
    found = registry.entries("encoders")
    assert found["acme-enc"].spec.description.startswith("acme: ")
    assert "acme.vision.enc" not in sys.modules
    # With the spec file missing, the error names the file and the top-level package looked in last.
    (package / "specs" / "encoders" / "acme-enc.toml").unlink()
    with pytest.warns(registry.PluginWarning, match=r"no spec file specs/encoders/acme-enc.toml in package 'acme'"):
        registry.entries("encoders")
