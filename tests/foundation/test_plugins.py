import importlib.metadata as md
import os
import subprocess
import sys
from dataclasses import dataclass

import pytest

from tests.foundation.plugin_util import install_tiny_plugin
from tnf import TnfError
from tnf.generators import Generator
from tnf.objects import ObjectSource
from tnf.registry import Registry


class FakeSensor:
    """A sensor from a fake distribution."""

    @dataclass
    class Config:
        width: int = 4

    def __init__(self, cfg):
        self.cfg = cfg


def fake_entry_points(mapping):
    class Dist:
        name = "tnf-fake"

    def entry_points(group=None, **_):
        eps = []
        for name, value in mapping.get(group, {}).items():
            ep = md.EntryPoint(name=name, value=value, group=group)
            object.__setattr__(ep, "dist", Dist())  # EntryPoint is immutable; real ones carry their dist
            eps.append(ep)
        return md.EntryPoints(eps)

    return entry_points


def test_entry_point_from_fake_distribution(monkeypatch):
    monkeypatch.setattr(md, "entry_points", fake_entry_points({"tnf.sensors": {"fake": f"{__name__}:FakeSensor"}}))
    reg = Registry("sensor", "tnf.sensors")
    assert reg.names() == ["fake"]
    assert reg.entry("fake").origin == "tnf-fake"
    assert reg.build({"name": "fake", "width": 9}) is not None


def test_discovery_is_lazy(monkeypatch):
    calls = []

    def entry_points(group=None, **_):
        calls.append(group)
        return md.EntryPoints([])

    monkeypatch.setattr(md, "entry_points", entry_points)
    reg = Registry("sensor", "tnf.sensors")
    assert calls == []
    reg.names()
    reg.names()
    assert calls == ["tnf.sensors"]


def test_plugin_duplicate_of_in_tree_name_names_both(monkeypatch):
    monkeypatch.setattr(md, "entry_points", fake_entry_points({"tnf.sensors": {"digit": f"{__name__}:FakeSensor"}}))
    reg = Registry("sensor", "tnf.sensors")

    class Digit:
        @dataclass
        class Config:
            pass

    reg.add("digit", Digit, origin="tnf")
    with pytest.raises(TnfError, match=r"duplicate sensor 'digit'.*Digit \(from tnf\).*FakeSensor \(from tnf-fake\)"):
        reg.names()


def test_real_installed_plugin(tmp_path, monkeypatch):
    site = install_tiny_plugin(tmp_path / "site")
    monkeypatch.syspath_prepend(str(site))
    reg = Registry("sensor", "tnf.sensors")
    entry = reg.entry("tiny")
    assert entry.origin == "tnf-tiny-plugin"
    assert reg.build({"name": "tiny", "width": 16}).cfg.width == 16


def test_plugin_import_error_names_the_missing_dependency(tmp_path, monkeypatch):
    site = install_tiny_plugin(tmp_path / "site", broken=True)
    monkeypatch.syspath_prepend(str(site))
    reg = Registry("sensor", "tnf.sensors")
    with pytest.raises(TnfError, match=r"No module named 'tnf_missing_dependency_xyz'; install 'tnf_missing_depe"):
        reg.names()


@pytest.mark.parametrize(
    "target, error",
    [
        (
            "tnf_tiny_plugin.sensor:TinySensr",
            "AttributeError: module 'tnf_tiny_plugin.sensor' has no attribute 'TinySensr'",
        ),
        ("tnf_tiny_plugn.sensor:TinySensor", "ModuleNotFoundError: No module named 'tnf_tiny_plugn'"),
    ],
)
def test_a_misspelt_entry_point_is_one_line_naming_it(tmp_path, monkeypatch, target, error):
    monkeypatch.syspath_prepend(str(install_tiny_plugin(tmp_path / "site", sensor=target)))
    reg = Registry("sensor", "tnf.sensors")
    with pytest.raises(TnfError) as e:
        reg.entry("digit")  # a plugin that cannot load stops every lookup, saying which and why
    assert str(e.value) == (
        f"sensor 'tiny' (tnf.sensors entry point {target!r} of tnf-tiny-plugin) cannot be loaded: {error}; "
        "fix the entry point in tnf-tiny-plugin's pyproject.toml and reinstall it"
    )


def test_plugin_yaml_joins_config_groups(tmp_path, monkeypatch):
    from tnf.testing import compose

    site = install_tiny_plugin(tmp_path / "site")
    monkeypatch.syspath_prepend(str(site))
    cfg = compose("touch", ["sensor=tiny"])
    assert cfg.sensor.name == "tiny" and cfg.sensor.width == 8


@pytest.mark.parametrize("package", ["tnf_tiny_plugin.cnf", "tnf_tiny_plugn.conf"])
def test_a_misspelt_conf_entry_point_is_one_line_naming_it(tmp_path, monkeypatch, package):
    """Hydra skips a search path that is no package; its options would then be unknown, the plugin's YAML unread."""
    from tnf.testing import compose

    monkeypatch.syspath_prepend(str(install_tiny_plugin(tmp_path / "site", conf=package)))
    with pytest.raises(TnfError) as e:
        compose("touch", ["sensor=tiny"])
    assert str(e.value) == (
        f"tnf.conf entry point 'tiny' of tnf-tiny-plugin names {package!r}, which is not installed; "
        "fix the entry point in tnf-tiny-plugin's pyproject.toml and reinstall it"
    )


def test_plugin_yaml_absent_without_plugin():
    from hydra.errors import MissingConfigException

    from tnf.testing import compose

    with pytest.raises(MissingConfigException):
        compose("touch", ["sensor=tiny"])


def test_cli_list_shows_plugin_origin(tmp_path):
    site = install_tiny_plugin(tmp_path / "site")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(site), os.environ.get("PYTHONPATH", "")])}
    out = subprocess.run([sys.executable, "-m", "tnf.cli", "list"], capture_output=True, text=True, env=env)
    assert out.returncode == 0, out.stderr
    rows = [line for line in out.stdout.splitlines() if " tiny " in line]
    assert rows and "tnf-tiny-plugin" in rows[0], out.stdout
    for name in ("digit", "omnitact", "hashgrid", "nerf", "tn_cgan", "warp_gel", "builtin"):
        assert f" {name} " in out.stdout


def test_in_tree_components_are_tnf_entry_points():
    """pyproject.toml's tnf.* entry points are what the install lists and what the registries hold."""
    tomllib = pytest.importorskip("tomllib")
    from pathlib import Path

    from tnf.registry import REGISTRIES

    pyproject = tomllib.loads((Path(__file__).resolve().parents[2] / "pyproject.toml").read_text())
    declared = {
        (group, name, value)
        for group, eps in pyproject["project"]["entry-points"].items()
        if group.startswith("tnf.")
        for name, value in eps.items()
    }
    installed = {
        (ep.group, ep.name, ep.value) for ep in md.distribution("tnf").entry_points if ep.group != "console_scripts"
    }
    assert installed == declared, "tnf's installed entry points differ from pyproject.toml: run `pip install -e .`"
    registered = {(r.group, e.name) for r in REGISTRIES.values() for e in r.entries() if e.origin == "tnf"}
    assert registered == {(group, name) for group, name, _ in declared}
    assert {group for group, _, _ in declared} == {r.group for r in REGISTRIES.values()}


def test_source_tree_without_metadata_is_a_one_line_error():
    """Without site-packages (so without tnf's metadata), a lookup says to install tnf."""
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    code = "import tnf.registry as r; r.SENSORS.names()"
    out = subprocess.run(
        [sys.executable, "-S", "-c", code], capture_output=True, text=True, env={"PYTHONPATH": str(root)}, cwd=root
    )
    assert out.returncode == 1
    last = out.stderr.strip().splitlines()[-1]
    assert last.startswith("tnf.errors.TnfError: no sensor found: tnf's package metadata is missing"), out.stderr
    assert last.endswith("run `pip install -e .` in the checkout")


def test_cli_reports_missing_metadata_in_one_line(monkeypatch, capsys):
    from tnf import listing
    from tnf.cli import main

    def missing(name):
        raise md.PackageNotFoundError(name)

    monkeypatch.setattr(md, "entry_points", lambda group=None, **_: md.EntryPoints([]))
    monkeypatch.setattr(md, "distribution", missing)
    monkeypatch.setattr(listing, "REGISTRIES", {"objects": Registry("objects", "tnf.objects", in_tree=True)})
    assert main(["list"]) == 1
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "tnf's package metadata is missing" in err and "pip install -e ." in err, err


def test_stale_install_names_the_group(monkeypatch):
    monkeypatch.setattr(md, "entry_points", lambda group=None, **_: md.EntryPoints([]))
    reg = Registry("simulator", "tnf.simulators", in_tree=True)
    with pytest.raises(TnfError, match=r"no simulator found: tnf's installed metadata lists no 'tnf.simulators'"):
        reg.names()


def test_refresh_keeps_what_was_added_directly(tmp_path, monkeypatch):
    reg = Registry("sensor", "tnf.sensors")
    reg.add("stand_in", FakeSensor, origin="tests")
    assert "tiny" not in reg
    monkeypatch.syspath_prepend(str(install_tiny_plugin(tmp_path / "site")))
    reg.refresh()
    assert "tiny" in reg and "stand_in" in reg and "digit" in reg


def test_the_contract_wants_the_defaults_from_the_plugins_yaml(tmp_path, monkeypatch):
    """The contract suites' check passes for a plugin whose Config takes its defaults from its own YAML, and fails,
    saying what to do, for one that writes them in the code or takes them from another file."""
    from tnf.registry import FROM_YAML, yaml_defaults
    from tnf.testing import SensorContract

    monkeypatch.syspath_prepend(str(install_tiny_plugin(tmp_path / "site")))

    def check(sensor: type) -> None:
        registry = Registry("sensor", "tnf.no_such_group")
        registry.add("tiny", sensor, origin="tests")
        type("Check", (SensorContract,), {"registry": registry, "name": "tiny"})().test_config_defaults_are_its_yaml()

    from tnf_tiny_plugin.sensor import TinySensor

    check(TinySensor)
    with pytest.raises(AssertionError, match=r"decorate it with @yaml_defaults\(\"sensor/tiny\""):
        check(FakeSensor)
    other = tmp_path / "other" / "sensor"
    other.mkdir(parents=True)
    (other / "tiny.yaml").write_text("name: tiny\nwidth: 9\n")

    class Stale:
        @dataclass
        @yaml_defaults("sensor/tiny", conf=other.parent)
        class Config:
            width: int = FROM_YAML

    with pytest.raises(AssertionError, match="sensor=tiny composes other values than"):
        check(Stale)


class NotAGenerator:
    """A generator class that forgot tnf's base class."""

    @dataclass
    class Config:
        ngf: int = 4


class HalfGenerator(Generator):
    """Implements generate, but not training_step or configure_optimizers."""

    @dataclass
    class Config:
        ngf: int = 4

    def generate(self, batch):
        return batch["rgb"]


@pytest.mark.parametrize(
    ("target", "error"),
    [
        ("NotAGenerator", r"is not a subclass of tnf\.generators\.Generator; subclass it"),
        ("HalfGenerator", r"does not implement training_step, configure_optimizers of tnf\.generators\.Generator"),
    ],
)
def test_a_plugin_class_that_breaks_the_contract_is_one_line_at_discovery(monkeypatch, target, error):
    """Found when the registry discovers it, naming the class and its distribution, not as an AttributeError or a
    bare NotImplementedError deep in training."""
    from tnf.registry import GENERATORS

    group = {"tnf.generators": {"mine": f"{__name__}:{target}"}}
    monkeypatch.setattr(md, "entry_points", fake_entry_points(group))
    reg = Registry("generator", "tnf.generators", base=GENERATORS.base, required=GENERATORS.required)
    with pytest.raises(TnfError, match=rf"generator 'mine' \({__name__}\.{target} \(from tnf-fake\)\) {error}"):
        reg.names()


def test_an_object_source_may_override_load_or__load(monkeypatch):
    from tnf.registry import OBJECTS

    group = {"tnf.objects": {"captured": "tnf.objects.captured:Captured", "half": f"{__name__}:HalfSource"}}
    monkeypatch.setattr(md, "entry_points", fake_entry_points(group))
    reg = Registry("objects", "tnf.objects", base=OBJECTS.base, required=OBJECTS.required)
    with pytest.raises(TnfError, match=r"'half' .* does not implement _load \(or load\) of tnf\.objects\.ObjectSource"):
        reg.names()


class HalfSource(ObjectSource):
    """Lists names but loads nothing."""

    @dataclass
    class Config:
        pass

    def names(self):
        return ["a"]


class BrokenSensor:
    """A plugin sensor whose constructor fails."""

    @dataclass
    class Config:
        width: int = 4

    def __init__(self, cfg):
        raise ValueError("lookup table missing\nsecond line")


def test_a_plugin_component_that_fails_to_build_is_one_line_naming_it(monkeypatch):
    monkeypatch.setattr(md, "entry_points", fake_entry_points({"tnf.sensors": {"broken": f"{__name__}:BrokenSensor"}}))
    reg = Registry("sensor", "tnf.sensors")
    with pytest.raises(TnfError) as e:
        reg.build("broken")
    assert str(e.value) == (
        f"sensor 'broken' ({__name__}.BrokenSensor (from tnf-fake)) failed to build: ValueError: lookup table "
        "missing (HYDRA_FULL_ERROR=1 shows the traceback)"
    )
    assert isinstance(e.value.__cause__, ValueError)
