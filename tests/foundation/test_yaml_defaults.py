"""A Config takes its defaults from a YAML file (tnf.registry.yaml_defaults): each default is written once."""

from dataclasses import dataclass, fields
from pathlib import Path
from typing import ClassVar

import pytest

from tnf import TnfError
from tnf.registry import defaults_source, from_dict, yaml_defaults


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
        size: int
        scale: float
        shape: tuple[int, int]
        tags: list[str]
        path: str | None
        spots: list[Spot]
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
        width: int
        height: int

    @dataclass
    @yaml_defaults("sensor/small", conf=conf)
    class Small(Base):
        markers: bool

    assert Small() == Small(8, 6, True)
    assert [f.name for f in fields(Small)] == ["width", "height", "markers"]
    assert defaults_source(Base) is None


def test_a_section_of_a_file(tmp_path):
    conf = write(tmp_path, "stage/default", "name: run\nfit:\n  steps: 10\n  rate: 0.5\nother: 1\n")

    @dataclass
    @yaml_defaults("stage/default", conf=conf, node="fit")
    class Fit:
        steps: int
        rate: float

    assert Fit() == Fit(10, 0.5)
    assert defaults_source(Fit) == f"{conf / 'stage' / 'default.yaml'}#fit"


def test_partial_takes_only_the_keys_that_are_fields(tmp_path):
    conf = write(tmp_path, "stage/default", "views: 4\nambient: 0.3\n")

    @dataclass
    @yaml_defaults("stage/default", conf=conf, partial=True)
    class Lights:
        ambient: float

    assert Lights().ambient == 0.3


@pytest.mark.parametrize(
    "text, annotations, in_code, message",
    [
        ("size: 3\n", {"size": int, "scale": float}, {}, r"a\.yaml: no key 'scale', a field of Config$"),
        ("size: 3\nscael: 1.0\n", {"size": int}, {}, r"a\.yaml: key 'scael' is no field of Config$"),
        ("size: 3\n", {"size": int}, {"size": 3}, r"a\.yaml: Config\.size has a default in the code too"),
        ("size: big\n", {"size": int}, {}, r"a\.yaml: size: expected an integer, got 'big'$"),
        ("size: ${other}\n", {"size": int}, {}, r"a\.yaml: size is an interpolation"),
        ("- 3\n", {"size": int}, {}, r"a\.yaml: expected a mapping of settings"),
    ],
)
def test_a_file_that_does_not_fit_is_one_line_naming_file_and_key(tmp_path, text, annotations, in_code, message):
    conf = write(tmp_path, "a", text)
    config = type("Config", (), {"__annotations__": annotations, **in_code})
    with pytest.raises(TnfError, match=message) as err:
        yaml_defaults("a", conf=conf)(config)
    assert "\n" not in str(err.value) and str(tmp_path / "a.yaml") in str(err.value)


def test_a_missing_file_is_named(tmp_path):
    class Config:
        size: int

    with pytest.raises(TnfError, match=r"nothing\.yaml: no such file"):
        yaml_defaults("nothing", conf=tmp_path)(Config)
