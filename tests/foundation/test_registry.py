from dataclasses import dataclass, field
from typing import Literal

import pytest

from tnf import TnfError
from tnf.registry import REGISTRIES, Registry, config_to_dict, from_dict


def make_registry() -> Registry:
    reg = Registry("widget", "tnf.test_widgets")

    class Plain:
        """A plain widget."""

        @dataclass
        class Config:
            size: int = 3
            scale: float = 1.0
            mode: Literal["a", "b"] = "a"
            tags: list[str] = field(default_factory=list)
            shape: tuple[int, int] = (2, 2)
            path: str | None = None

            def validate(self):
                if self.size <= 0:
                    raise ValueError(f"size must be > 0, got {self.size}")

        def __init__(self, cfg, extra=None):
            self.cfg = cfg
            self.extra = extra

    reg.add("plain", Plain, origin="tnf")
    return reg


def test_register_build_and_defaults():
    reg = make_registry()
    w = reg.build({"name": "plain", "size": 5, "scale": 2}, extra="x")
    assert w.cfg.size == 5 and w.cfg.scale == 2.0 and isinstance(w.cfg.scale, float)
    assert w.cfg.mode == "a" and w.cfg.shape == (2, 2) and w.extra == "x"
    assert reg.build("plain").cfg.size == 3
    assert reg.names() == ["plain"] and "plain" in reg
    assert reg.entry("plain").origin == "tnf"
    assert config_to_dict(w.cfg) == {"size": 5, "scale": 2.0, "mode": "a", "tags": [], "shape": [2, 2], "path": None}


def test_duplicate_names_both_origins():
    reg = make_registry()

    class Other:
        @dataclass
        class Config:
            pass

    with pytest.raises(TnfError, match=r"duplicate widget 'plain'.*make_registry.<locals>.Plain.*Other"):
        reg.add("plain", Other, origin="some-plugin")
    reg.add("plain", reg.get("plain"), origin="tnf")  # the same object again is harmless


def test_unknown_name_lists_available():
    reg = make_registry()
    with pytest.raises(TnfError, match=r"unknown widget 'nope'; available: plain"):
        reg.get("nope")


@pytest.mark.parametrize(
    "params, message",
    [
        ({"sise": 3}, r"widget.plain: unknown key 'sise'; valid keys: mode, path, scale, shape, size, tags"),
        ({"size": "3"}, r"widget.plain.size: expected a whole number, got '3'"),
        ({"size": 2.5}, r"widget.plain.size: expected a whole number"),
        ({"size": True}, r"widget.plain.size: expected a whole number"),
        ({"scale": "big"}, r"widget.plain.scale: expected a number"),
        ({"mode": "c"}, r"widget.plain.mode: expected one of 'a', 'b', got 'c'"),
        ({"tags": "x"}, r"widget.plain.tags: expected a list"),
        ({"tags": [1]}, r"widget.plain.tags\[0\]: expected a string"),
        ({"shape": [1, 2, 3]}, r"widget.plain.shape: expected 2 values, got 3"),
        ({"size": -1}, r"widget.plain: size must be > 0, got -1"),
    ],
)
def test_config_validation_names_the_key(params, message):
    reg = make_registry()
    with pytest.raises(TnfError, match=message):
        reg.config("plain", params)


def test_nested_dataclass_config():
    @dataclass
    class Light:
        intensity: float = 1.0

    @dataclass
    class Cfg:
        lights: list[Light] = field(default_factory=list)

    cfg = from_dict(Cfg, {"lights": [{"intensity": 2}]})
    assert cfg.lights[0].intensity == 2.0
    with pytest.raises(TnfError, match=r"cfg.lights\[0\]: unknown key 'colour'"):
        from_dict(Cfg, {"lights": [{"colour": 2}]}, where="cfg")


def test_a_config_without_name_says_where_it_goes():
    reg = make_registry()
    with pytest.raises(TnfError) as e:
        reg.build({"size": 5, "tags": ["a"] * 100})
    assert str(e.value) == "a widget config needs a 'name' key: its registry name (`name: NAME` first in its YAML)"


def test_component_without_config_is_an_error():
    reg = Registry("widget", "tnf.test_widgets")
    reg.add("bare", object, origin="tnf")
    with pytest.raises(TnfError, match="declares no Config"):
        reg.config("bare")


def test_import_tnf_discovers_nothing():
    import subprocess
    import sys

    code = (
        "import sys, tnf, tnf.registry as r; "
        "assert not any(x._discovered for x in r.REGISTRIES.values()); "
        "assert 'torch' not in sys.modules and 'warp' not in sys.modules; print('ok')"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "ok"


def test_kinds():
    assert set(REGISTRIES) == {"objects", "scene", "sensor", "simulator", "generator"}
    assert {r.group for r in REGISTRIES.values()} == {
        "tnf.objects",
        "tnf.scenes",
        "tnf.sensors",
        "tnf.simulators",
        "tnf.generators",
    }


def _float_fields():
    """(registry, component, field) for every top-level float setting of every registered component."""
    import dataclasses
    import types
    import typing

    out = []
    for reg in REGISTRIES.values():
        for entry in reg.entries():
            cls = entry.config_class
            if cls is None or not dataclasses.is_dataclass(cls):
                continue
            hints = typing.get_type_hints(cls)
            for f in dataclasses.fields(cls):
                tp = hints[f.name]
                if tp is float or (
                    typing.get_origin(tp) in (typing.Union, types.UnionType) and float in typing.get_args(tp)
                ):
                    out.append((reg, entry.name, f.name))
    return out


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), float("-inf")])
def test_every_float_setting_refuses_non_finite_values(bad):
    fields = _float_fields()
    assert len(fields) > 50  # sensors, simulator, scenes, generators, object sources
    for reg, name, key in fields:
        with pytest.raises(TnfError, match=rf"{reg.kind}\.{name}\.{key}: expected a finite number"):
            reg.config(name, {key: bad})
