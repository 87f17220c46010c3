"""What every contract suite checks of a registered component: its config and its documentation."""

from __future__ import annotations

import ast
import dataclasses
import inspect
import json
import textwrap
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import pytest

from tnf.errors import TnfError
from tnf.registry import (
    Registry,
    config_to_dict,
    defaults_source,
    split_spec,
)
from tnf.testing.config import compose


def undocumented_fields(config_class: type) -> list[str]:
    """Fields of a Config dataclass (and its dataclass bases) without a docstring right below them."""
    missing = []
    for klass in config_class.__mro__:
        if klass is object or not dataclasses.is_dataclass(klass):
            continue
        try:
            tree = ast.parse(textwrap.dedent(inspect.getsource(klass)))
        except (OSError, TypeError):  # no source (e.g. built dynamically): nothing to check
            continue
        body = tree.body[0].body  # type: ignore[attr-defined]
        for stmt, nxt in zip(body, body[1:] + [None]):
            if isinstance(stmt, ast.AnnAssign) and isinstance(stmt.target, ast.Name):
                doc = isinstance(nxt, ast.Expr) and isinstance(nxt.value, ast.Constant)
                if not (doc and isinstance(nxt.value.value, str)):  # type: ignore[union-attr]
                    missing.append(f"{klass.__qualname__}.{stmt.target.id}")
    return missing


class _ComponentContract:
    """Checks shared by every kind: registration, documentation and the config round trip."""

    registry: ClassVar[Registry]
    name: ClassVar[str]
    """Registry name of the component under test."""
    params: ClassVar[dict[str, Any]] = {}
    """Config overrides used to build it (keep tests tiny)."""

    @classmethod
    def spec(cls) -> dict[str, Any]:
        """``{"name": name, **params}``: the config node the component is built from."""
        return {"name": cls.name, **cls.params}

    def test_registered_with_description(self):
        entry = self.registry.entry(self.name)
        doc = (entry.obj.__doc__ or "").strip()
        assert doc, f"{entry.obj.__qualname__} needs a docstring: its first line is what `tnf list` shows"
        assert dataclasses.is_dataclass(entry.config_class), "the component must declare a nested Config dataclass"

    def test_config_fields_documented(self):
        missing = undocumented_fields(self.registry.entry(self.name).config_class)
        assert not missing, f"Config fields need a docstring below them (units): {missing}"

    def test_config_round_trip(self):
        cfg = self.registry.config(self.name, self.params)
        data = config_to_dict(cfg)
        assert json.loads(json.dumps(data)) == data, "config_to_dict must give plain JSON data"
        again = self.registry.config(self.name, data)
        assert config_to_dict(again) == data
        for k, v in self.params.items():
            assert _close(data[k], v), f"override {k}={v!r} did not reach the config ({data[k]!r})"

    def test_unknown_key_is_an_error_naming_it(self):
        with pytest.raises(TnfError, match="no_such_key"):
            self.registry.config(self.name, {**self.params, "no_such_key": 1})

    def test_config_defaults_are_its_yaml(self):
        """The Config takes its defaults from the option named like the component (``conf/<kind>/<name>.yaml``,
        through ``@yaml_defaults``), so that ``<kind>=<name>`` on the command line and ``build("<name>")`` in code
        agree, and each default is written once."""
        from hydra.errors import MissingConfigException

        group = self.registry.kind  # the config group has the registry's kind as its name
        try:
            node = compose("touch", [f"{group}={self.name}"])[group]
        except MissingConfigException:
            pytest.skip(f"no conf/{group}/{self.name}.yaml: {self.name} is built in code only")
        cls = self.registry.entry(self.name).config_class
        source = defaults_source(cls)
        assert source is not None and Path(source).parts[-2:] == (group, f"{self.name}.yaml"), (
            f"{cls.__qualname__} takes its defaults from {source}: decorate it with "
            f'@yaml_defaults("{group}/{self.name}", conf=<your package\'s conf folder>) under @dataclass'
        )
        _, params = split_spec(node)
        assert config_to_dict(cls()) == params, f"{group}={self.name} composes other values than {source} holds"


def _close(a: Any, b: Any) -> bool:
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return len(a) == len(b) and all(_close(x, y) for x, y in zip(a, b))
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_close(a[k], b[k]) for k in a)
    if isinstance(a, float) or isinstance(b, float):
        return bool(np.isclose(a, b))
    return bool(a == b)
