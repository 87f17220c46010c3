"""A Config takes its defaults from a YAML file (tnf.registry.yaml_defaults): each default is written once."""

import copy
import pickle
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any, ClassVar

import pytest

from tnf import TnfError
from tnf.registry import FROM_YAML, IN_TREE, REGISTRIES, config_to_dict, defaults_source, from_dict, yaml_defaults


@dataclass
class Spot:
    position: tuple[float, float]
    """Where it is, metres."""
    power: float
    """How bright it is."""


def write(folder: Path, option: str, text: str) -> Path:
    path = folder / f"{option}.yaml"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return folder


def test_fields_take_the_files_values_validated(tmp_path):
    conf = write(
        tmp_path,
        "widget/plain",
        "name: plain\nsize: 3\nscale: 2\nshape: [2, 4]\ntags: [a]\npath: null\nspots: [{position: [0, 1], power: 2}]\n",
    )

    @dataclass
    @yaml_defaults("widget/plain", conf=conf)
    class Config:
        size: int = FROM_YAML
        scale: float = FROM_YAML
        shape: tuple[int, int] = FROM_YAML
        tags: list[str] = FROM_YAML
        path: str | None = FROM_YAML
        spots: list[Spot] = FROM_YAML
        kinds: ClassVar[tuple[str, ...]] = ("not", "a", "field")

    cfg = Config()
    assert (cfg.size, cfg.scale, cfg.shape, cfg.tags, cfg.path) == (3, 2.0, (2, 4), ["a"], None)
    assert isinstance(cfg.scale, float) and cfg.spots == [Spot((0.0, 1.0), 2.0)]
    assert [f.name for f in fields(Config)] == ["size", "scale", "shape", "tags", "path", "spots"]
    assert defaults_source(Config) == str(conf / "widget" / "plain.yaml")
    # Each instance has its own lists: changing one changes no other, nor the defaults.
    cfg.tags.append("b")
    cfg.spots[0].power = 5.0
    assert Config().tags == ["a"] and Config().spots[0].power == 2.0
    assert Config(size=7).size == 7 and from_dict(Config, {"scale": 1}).scale == 1.0


def test_inherited_fields_take_the_files_values_too(tmp_path):
    conf = write(tmp_path, "sensor/small", "name: small\nwidth: 8\nheight: 6\nmarkers: true\n")

    @dataclass
    class Base:
        width: int = FROM_YAML
        height: int = FROM_YAML

    @dataclass
    @yaml_defaults("sensor/small", conf=conf)
    class Small(Base):
        markers: bool = FROM_YAML

    assert Small() == Small(8, 6, True)
    assert [f.name for f in fields(Small)] == ["width", "height", "markers"]
    assert defaults_source(Base) is None


def test_a_section_of_a_file(tmp_path):
    conf = write(tmp_path, "stage/default", "name: run\nfit:\n  steps: 10\n  rate: 0.5\nother: 1\n")

    @dataclass
    @yaml_defaults("stage/default", conf=conf, node="fit")
    class Fit:
        steps: int = FROM_YAML
        rate: float = FROM_YAML

    assert Fit() == Fit(10, 0.5)
    assert defaults_source(Fit) == f"{conf / 'stage' / 'default.yaml'}#fit"


def test_partial_takes_only_the_keys_that_are_fields(tmp_path):
    conf = write(tmp_path, "stage/default", "views: 4\nambient: 0.3\n")

    @dataclass
    @yaml_defaults("stage/default", conf=conf, partial=True)
    class Lights:
        ambient: float = FROM_YAML

    assert Lights().ambient == 0.3


@pytest.mark.parametrize(
    "text, annotations, in_code, message",
    [
        (
            "size: 3\n",
            {"size": int, "scale": float},
            {"scale": FROM_YAML},
            r"a\.yaml: no key 'scale', a field of Config$",
        ),
        ("size: 3\nscael: 1.0\n", {"size": int}, {}, r"a\.yaml: key 'scael' is no field of Config$"),
        ("size: 3\n", {"size": int}, {"size": 3}, r"a\.yaml: Config\.size has a default in the code too"),
        ("size: 3\n", {"size": int, "scale": float}, {"scale": None}, r"a\.yaml: Config\.scale has a default in"),
        ("size: 3\nscale: 1\n", {"size": int, "scale": float}, {}, r"a\.yaml: Config\.scale has no default; wr"),
        ("size: big\n", {"size": int}, {}, r"a\.yaml: size: expected a whole number, got 'big'$"),
        ("size: ${other}\n", {"size": int}, {}, r"a\.yaml: size is an interpolation"),
        ("- 3\n", {"size": int}, {}, r"a\.yaml: expected a mapping of settings"),
    ],
)
def test_a_file_that_does_not_fit_is_one_line_naming_file_and_key(tmp_path, text, annotations, in_code, message):
    conf = write(tmp_path, "a", text)
    config = type("Config", (), {"__annotations__": annotations, "size": FROM_YAML, **in_code})
    with pytest.raises(TnfError, match=message) as err:
        yaml_defaults("a", conf=conf)(config)
    assert "\n" not in str(err.value) and str(tmp_path / "a.yaml") in str(err.value)


def test_a_name_other_than_the_options_is_one_line(tmp_path):
    """``name`` selects the component that ``sensor=small`` builds: it must be the option's own."""
    conf = write(tmp_path, "sensor/small", "name: smal\nwidth: 8\n")
    config = type("Config", (), {"__annotations__": {"width": int}, "width": FROM_YAML})
    with pytest.raises(TnfError, match=r"small\.yaml: name 'smal' is not the file's; write `name: small`$"):
        yaml_defaults("sensor/small", conf=conf)(config)


def test_above_dataclass_is_one_line_saying_where_it_goes(tmp_path):
    """Over a finished dataclass the YAML's values would miss ``__init__``: ``Config()`` would hold FROM_YAML."""
    conf = write(tmp_path, "sensor/small", "name: small\nwidth: 8\n")
    with pytest.raises(
        TnfError, match=r"small\.yaml: \S*Small is a dataclass already; put @yaml_defaults under @dataclass$"
    ):

        @yaml_defaults("sensor/small", conf=conf)
        @dataclass
        class Small:
            width: int = FROM_YAML


def test_a_subclass_that_is_no_dataclass_is_named(tmp_path):
    """A Config subclass without ``@dataclass`` has its base's fields only: its own are named, not unknown keys."""
    conf = write(tmp_path, "sensor/small", "name: small\nwidth: 8\nmarkers: true\n")

    @dataclass
    class Base:
        width: int = FROM_YAML

    @yaml_defaults("sensor/small", conf=conf)
    class Small(Base):
        markers: bool = FROM_YAML

    with pytest.raises(TnfError, match=r"^sensor: \S*Small\.markers is no field: decorate \S*Small with @dataclass$"):
        from_dict(Small, {"markers": False}, where="sensor")


def test_a_missing_file_is_named(tmp_path):
    class Config:
        size: int = FROM_YAML

    with pytest.raises(TnfError, match=r"nothing\.yaml: no such file"):
        yaml_defaults("nothing", conf=tmp_path)(Config)


def test_a_plugin_config_without_conf_is_told_to_give_its_folder():
    """A plugin's Config that leaves out ``conf=`` is looked up in tnf's own conf/: the error says to pass its
    package's folder, not only that tnf's file is missing."""

    class Config:
        size: int = FROM_YAML

    with pytest.raises(TnfError, match=r"tiny_p2p\.yaml: no such file; .*Config is not tnf's own, so give its package"):
        yaml_defaults("generator/tiny_p2p")(Config)


def test_a_field_left_from_yaml_without_a_value_stops_the_import(tmp_path, monkeypatch):
    """A Config module whose YAML lacks one of its fields fails to import, with the one line naming file and key."""
    package = tmp_path / "stray_widgets"
    write(package / "conf", "widget/plain", "size: 3\n")
    (package / "__init__.py").write_text(
        "from dataclasses import dataclass\n"
        "from pathlib import Path\n\n"
        "from tnf.registry import FROM_YAML, yaml_defaults\n\n\n"
        "@dataclass\n"
        '@yaml_defaults("widget/plain", conf=Path(__file__).parent / "conf")\n'
        "class Config:\n"
        "    size: int = FROM_YAML\n"
        "    scale: float = FROM_YAML\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    with pytest.raises(TnfError, match=r"plain\.yaml: no key 'scale', a field of Config$"):
        import stray_widgets  # noqa: F401


def test_a_class_that_writes_from_yaml_without_the_decorator_gets_no_values():
    @dataclass
    class Config:
        size: int = FROM_YAML
        scale: float = FROM_YAML

    with pytest.raises(
        TnfError, match=r"^widget: no value for 'scale' \(FROM_YAML in a class without @yaml_defaults\)$"
    ):
        from_dict(Config, {"size": 3}, where="widget")


def test_every_config_needs_no_arguments_and_holds_the_yaml_values():
    """``X.Config()`` holds the YAML's values, as the command line does: no field is left FROM_YAML."""
    from tnf.capture import CaptureConfig
    from tnf.eval.classify import ClassifierConfig
    from tnf.real.calibrate import FitSettings as CalibrateFit
    from tnf.scenes.system import FitSettings

    stages = [CaptureConfig, ClassifierConfig, CalibrateFit, FitSettings]
    entries = [e for r in REGISTRIES.values() for e in r.entries() if e.config_class is not None]
    assert all(defaults_source(e.config_class) is not None for e in entries if e.origin == IN_TREE)
    components = [e.config_class for e in entries if defaults_source(e.config_class) is not None]  # plugins too
    for cls in stages + components:
        values = config_to_dict(cls())
        assert values and FROM_YAML not in leaves(values), f"{cls.__qualname__}: {values}"


def leaves(x: Any) -> list[Any]:
    if isinstance(x, dict):
        return [v for value in x.values() for v in leaves(value)]
    if isinstance(x, list):
        return [v for value in x for v in leaves(value)]
    return [x]


def test_from_yaml_is_one_object_that_copies_and_pickles_as_itself():
    assert repr(FROM_YAML) == "FROM_YAML" and type(FROM_YAML)() is FROM_YAML
    assert copy.copy(FROM_YAML) is FROM_YAML and copy.deepcopy([FROM_YAML])[0] is FROM_YAML
    assert pickle.loads(pickle.dumps(FROM_YAML)) is FROM_YAML


def test_field_metadata_sets_identity_and_hints(tmp_path):
    """``yaml_field`` keeps its metadata: a field outside identity is left out of artifact keys, and a refused
    value's message ends with the field's hint."""
    from dataclasses import field

    from tnf.artifacts import config_hash, identity
    from tnf.registry import SettingError, at_least, yaml_field

    conf = write(tmp_path, "stage/default", "size: 3\nbatch: 8\nredo: false\nnested: {depth: 2, workers: 1}\n")

    @dataclass
    @yaml_defaults("stage/default", conf=conf, node="nested")
    class Nested:
        depth: int = FROM_YAML
        workers: int = yaml_field(identity=False)

    @dataclass
    @yaml_defaults("stage/default", conf=conf)
    class Settings:
        size: int = FROM_YAML
        batch: int = yaml_field(identity=False)
        redo: bool = yaml_field(identity=False, hint=" (it redoes finished items)")
        nested: Nested = field(default=FROM_YAML)

        def validate(self) -> None:
            at_least(self, 1, "batch")
            if self.size > 10:
                raise SettingError("size", f"must be <= 10, got {self.size}")

    s = Settings()
    assert (s.size, s.batch, s.redo, s.nested) == (3, 8, False, Nested(2, 1))
    assert identity(s) == {"size": 3, "nested": {"depth": 2}}
    assert config_hash({"s": from_dict(Settings, {"batch": 2, "nested": {"workers": 4}})}) == config_hash({"s": s})
    assert config_hash({"s": from_dict(Settings, {"size": 4})}) != config_hash({"s": s})
    for data, message in [
        ({"redo": 3}, r"^stage\.redo: expected true or false, got 3 \(it redoes finished items\)$"),
        ({"batch": 0}, r"^stage\.batch: must be >= 1, got 0$"),
        ({"size": 11}, r"^stage\.size: must be <= 10, got 11$"),
        ({"nested": {"depth": 1.5}}, r"^stage\.nested\.depth: expected a whole number, got 1\.5$"),
    ]:
        with pytest.raises(TnfError, match=message):
            from_dict(Settings, data, where="stage")


def test_an_interpolation_of_another_section_takes_its_default(tmp_path):
    conf = write(tmp_path, "touch/default", "radius: 0.15\n")
    write(conf, "generate/default", "radius: ${touch.radius}\n")

    @dataclass
    @yaml_defaults("generate/default", conf=conf)
    class Settings:
        radius: float = FROM_YAML

    assert Settings().radius == 0.15
