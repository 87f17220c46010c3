"""Validated settings dataclasses: a component's ``Config`` or a stage's settings, built from YAML.

``from_dict`` builds a dataclass from a mapping (a Hydra node), checking every key and value type against the
class's annotations and running its ``validate()``. ``yaml_defaults`` gives each field its default from the YAML
file that users read and override (``name: type = FROM_YAML``), and ``yaml_field`` marks a field that is no part
of an artifact's identity (``IDENTITY``) or carries a hint for refused values (``HINT``).

``tnf.registry`` re-exports every public name here; components and plugins import them from there.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import inspect
import math
import os
import re
import types
import typing
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, TypeVar

from tnf.env import conf_dir
from tnf.errors import TnfError

T = TypeVar("T")


def plain(x: Any) -> Any:
    """``x`` as plain data: OmegaConf containers resolved, mappings as dicts, tuples and lists as lists."""
    try:  # OmegaConf containers, without importing omegaconf when not needed
        from omegaconf import DictConfig, ListConfig, OmegaConf

        if isinstance(x, (DictConfig, ListConfig)):
            return OmegaConf.to_container(x, resolve=True)
    except ImportError:  # pragma: no cover
        pass
    if isinstance(x, Mapping):
        return {k: plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [plain(v) for v in x]
    return x


# -- config validation ------------------------------------------------------------------------------
def from_dict(cls: type[T], data: Mapping[str, Any], where: str = "config") -> T:
    """Build dataclass ``cls`` from ``data``, checking keys and value types.

    Unknown keys, values of the wrong type and fields left ``FROM_YAML`` are errors that name the key as
    ``<where>.<key>`` (the key alone where ``where`` is empty: run-wide settings at the top of the config).
    """
    data = plain(data)
    if not isinstance(data, dict):
        raise TnfError(f"{where}: expected a mapping, got {type(data).__name__}")
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}  # type: ignore[arg-type]
    unknown = sorted(set(data) - set(fields))
    if unknown:
        if "__dataclass_fields__" not in cls.__dict__ and unknown[0] in inspect.get_annotations(cls):
            # A subclass of a dataclass, not one itself: its fields are its base's
            name = cls.__qualname__
            raise TnfError(f"{where}: {name}.{unknown[0]} is no field: decorate {name} with @dataclass")
        raise TnfError(f"{where}: unknown key {unknown[0]!r}; valid keys: {', '.join(sorted(fields))}")
    prefix = f"{where}." if where else ""  # where "": the settings at the top of the config, named alone
    hints = typing.get_type_hints(cls)
    kwargs = {}
    for k, v in data.items():
        try:
            kwargs[k] = _coerce(v, hints[k], f"{prefix}{k}")
        except TnfError as e:
            hint = fields[k].metadata.get(HINT)
            raise (TnfError(f"{e}{hint}") if hint else e) from None
    try:
        obj = cls(**kwargs)
    except (TypeError, ValueError) as e:
        raise TnfError(f"{where}: {e}") from None
    unset = [k for k in fields if getattr(obj, k) is FROM_YAML]
    if unset:
        raise TnfError(f"{where}: no value for {unset[0]!r} (FROM_YAML in a class without @yaml_defaults)")
    check = getattr(obj, "validate", None)
    if callable(check):
        try:
            check()
        except SettingError as e:
            raise TnfError(f"{prefix}{e.field}: {e.message}") from None
        except (ValueError, AssertionError) as e:
            raise TnfError(f"{where}: {e}") from None
    return obj


class SettingError(ValueError):
    """What ``validate()`` raises about one field: ``from_dict`` names it ``<where>.<field>: <message>``."""

    def __init__(self, field: str, message: str):
        super().__init__(f"{field}: {message}")
        self.field = field
        self.message = message


def at_least(settings: Any, minimum: float, *names: str) -> None:
    """Raise a ``SettingError`` for the first of the fields ``names`` of ``settings`` below ``minimum`` (None
    passes: an unset optional setting)."""
    for name in names:
        value = getattr(settings, name)
        if value is not None and value < minimum:
            raise SettingError(name, f"must be >= {minimum}, got {value}")


def _coerce(value: Any, tp: Any, where: str) -> Any:
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if tp is Any:
        return value
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        switch = _switch_names(args)
        if switch is not None:  # true, false or a name
            if isinstance(value, bool) or value in switch:
                return value
            raise TnfError(f"{where}: expected true, false or one of {', '.join(switch)}, got {value!r}")
        errors = []
        own = []  # the messages of the types of the value's kind (a NaN's float, a list's list): they say more
        for a in args:
            if a is type(None):
                continue
            try:
                return _coerce(value, a, where)
            except TnfError as e:
                errors.append(str(e))
                if _of_kind(value, a):
                    own.append(str(e))
        if len(errors) == 1 or len(own) == 1:  # one type besides None (an optional setting), or of the kind
            raise TnfError(own[0] if len(own) == 1 else errors[0])
        raise TnfError(f"{where}: expected {_name(tp)}, got {value!r}")
    if origin is typing.Literal:
        if value not in args:
            raise TnfError(f"{where}: expected one of {', '.join(map(repr, args))}, got {value!r}")
        return value
    if origin in (list, tuple) or tp in (list, tuple):
        if not isinstance(value, (list, tuple)):
            raise TnfError(f"{where}: expected a list, got {value!r}")
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(args) != len(value):
                raise TnfError(f"{where}: expected {len(args)} values, got {len(value)}")
            return tuple(_coerce(v, a, f"{where}[{i}]") for i, (v, a) in enumerate(zip(value, args)))
        inner = args[0] if args else Any
        items = [_coerce(v, inner, f"{where}[{i}]") for i, v in enumerate(value)]
        return tuple(items) if (origin is tuple or tp is tuple) else items
    if origin is dict or tp is dict:
        if not isinstance(value, Mapping):
            raise TnfError(f"{where}: expected a mapping, got {value!r}")
        inner = args[1] if len(args) == 2 else Any
        return {k: _coerce(v, inner, f"{where}.{k}") for k, v in value.items()}
    if dataclasses.is_dataclass(tp) and isinstance(tp, type):
        if isinstance(value, tp):
            return value
        return from_dict(tp, value, where)
    if tp is bool:
        if not isinstance(value, bool):
            raise TnfError(f"{where}: expected true or false, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise TnfError(f"{where}: expected a whole number, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise TnfError(f"{where}: expected a number, got {value!r}")
        if not math.isfinite(value):  # NaN passes every `x < 0` check: refuse it (and infinity) here, once
            raise TnfError(f"{where}: expected a finite number, got {value!r}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise TnfError(f"{where}: expected a string, got {value!r}")
        return value
    return value


def _of_kind(value: Any, tp: Any) -> bool:
    """Whether ``value`` is of the kind of type ``tp`` (a number for int or float, a list for a list or tuple, a
    string for str), whatever its content."""
    base = typing.get_origin(tp) or tp
    if isinstance(value, bool):
        return base is bool
    if base in (int, float):
        return isinstance(value, (int, float))
    if base in (list, tuple):
        return isinstance(value, (list, tuple))
    return isinstance(base, type) and base in (str, dict) and isinstance(value, base)


def _name(tp: Any) -> str:
    return getattr(tp, "__name__", None) or str(tp).replace("typing.", "")


def _switch_names(args: tuple[Any, ...]) -> tuple[str, ...] | None:
    """The names of a ``bool | Literal[names...]`` type's ``args`` (a switch that also takes a name); None for
    any other union."""
    rest = [a for a in args if a is not type(None)]
    if len(rest) != 2 or bool not in rest:
        return None
    other = rest[1] if rest[0] is bool else rest[0]
    if typing.get_origin(other) is not typing.Literal:
        return None
    return tuple(str(a) for a in typing.get_args(other))


# -- defaults from YAML -----------------------------------------------------------------------------
class _FromYaml:
    """The default of a Config field whose value is in the component's YAML (one instance: ``FROM_YAML``)."""

    _instance: _FromYaml | None = None

    def __new__(cls) -> _FromYaml:
        if cls._instance is None:
            cls._instance = super().__new__(cls)
        return cls._instance

    def __repr__(self) -> str:
        return "FROM_YAML"

    def __copy__(self) -> _FromYaml:
        return self

    def __deepcopy__(self, memo: dict[int, Any]) -> _FromYaml:
        return self

    def __reduce__(self) -> str:
        return "FROM_YAML"


FROM_YAML: Any = _FromYaml()
"""A Config field's default when ``yaml_defaults`` puts the YAML's value there: ``ngf: int = FROM_YAML``.

Typed ``Any`` so that type checkers see a default of every field's type, and ``Config()`` type-checks."""


def yaml_defaults(
    option: str, conf: str | os.PathLike[str] | None = None, node: str | None = None, partial: bool = False
) -> Callable[[type[T]], type[T]]:
    """Class decorator, under ``@dataclass``: every field's default is its value in ``<conf>/<option>.yaml``.

    Each field of the class is written ``name: type = FROM_YAML`` (or ``= yaml_field(...)``, with metadata); this
    puts the file's value in its place. A value that interpolates another section's setting (``${touch.radius}``
    in ``generate/default.yaml``) takes that setting's value in ``<conf>/<section>/default.yaml``.

    ``option`` is a config group option such as ``"generator/tn_cgan"``; ``conf`` the folder of the YAML files,
    tnf's own ``conf/`` (``tnf.env.conf_dir``) unless given (a plugin passes its package's ``conf`` folder).
    ``node`` takes the defaults from one section of the file (``"fit"`` in ``calibrate/default``). Inherited
    dataclass fields take the file's values too. The YAML values are validated as ``from_dict`` does; lists,
    dicts and dataclasses are copied for each instance.

    Errors at import, each one line naming the file and the key: a field without a value in the file, a key of
    the file without a field (``name``, the registry name, aside; ``partial=True`` takes only the file's keys
    that are fields, for a Config that shares some of a stage's settings), a ``name`` other than the option's
    (``sensor/NAME``), a field of the class whose default is not ``FROM_YAML`` (a value written in the code too,
    or none at all), and a class made a dataclass before this decorator ran (it goes under ``@dataclass``).
    """

    def apply(cls: type[T]) -> type[T]:
        root = Path(conf if conf is not None else conf_dir())
        path = root / f"{option}.yaml"
        where = f"{path}" + (f" ({node})" if node else "")
        if "__dataclass_fields__" in cls.__dict__:  # its __init__ keeps FROM_YAML as every default
            raise TnfError(f"{where}: {cls.__qualname__} is a dataclass already; put @yaml_defaults under @dataclass")
        if conf is None and not path.is_file() and cls.__module__.split(".")[0] != "tnf":
            raise TnfError(
                f"{path}: no such file; {cls.__module__}.{cls.__qualname__} is not tnf's own, so give its package's "
                f'folder: @yaml_defaults({option!r}, conf=Path(__file__).parent / "conf")'
            )
        values = _yaml_values(path, node, where)  # interpolations still as written
        hints = typing.get_type_hints(cls)
        own = inspect.get_annotations(cls)
        declared = [k for k in own if typing.ClassVar not in (hints[k], typing.get_origin(hints[k]))]
        inherited = [
            f.name
            for base in cls.__mro__[1:]
            if dataclasses.is_dataclass(base)
            for f in dataclasses.fields(base)
            if f.name not in own
        ]
        names = list(dict.fromkeys(declared + inherited))
        for k in declared:
            if k not in cls.__dict__:
                raise TnfError(f"{where}: {cls.__qualname__}.{k} has no default; write `{k}: ... = FROM_YAML`")
            if _declared_default(cls.__dict__[k]) is not FROM_YAML:
                raise TnfError(f"{where}: {cls.__qualname__}.{k} has a default in the code too; write it once, here")
        for k in names:
            if k not in values:
                raise TnfError(f"{where}: no key {k!r}, a field of {cls.__qualname__}")
        for k in values:
            if k not in names and not partial and not (k == "name" and node is None):
                raise TnfError(f"{where}: key {k!r} is no field of {cls.__qualname__}")
        option_name = Path(option).name
        if node is None and "name" not in names and values.get("name", option_name) != option_name:
            raise TnfError(f"{where}: name {values['name']!r} is not the file's; write `name: {option_name}`")
        for k in names:  # the fields' values only: a partial file's other keys may interpolate anything
            v = values[k]
            if isinstance(v, str) and "${" in v:
                values[k] = _section_default(root, v, f"{where}: {k}")
        annotations = dict(own)
        for k in names:
            value = _coerce(values[k], hints[k], f"{where}: {k}")
            annotations.setdefault(k, hints[k])  # an inherited field, declared again to take this file's default
            declared_as = cls.__dict__.get(k)
            if isinstance(declared_as, dataclasses.Field):  # yaml_field(...): its metadata stays
                if _shareable(value):
                    declared_as.default = value
                else:
                    declared_as.default = dataclasses.MISSING
                    declared_as.default_factory = functools.partial(copy.deepcopy, value)
            elif _shareable(value):
                setattr(cls, k, value)
            else:  # a list, a dict, a dataclass: each instance gets its own copy
                setattr(cls, k, dataclasses.field(default_factory=functools.partial(copy.deepcopy, value)))
        cls.__annotations__ = annotations
        cls._yaml_defaults = str(path) if node is None else f"{path}#{node}"  # type: ignore[attr-defined]
        return cls

    return apply


IDENTITY = "identity"
"""Field metadata key: ``False`` for a setting that changes how a stage runs (a batch size, a device, a redo
switch) but not what it makes, or a test ``settings -> bool`` for one that matters only with another setting's
value; ``tnf.artifacts.identity`` leaves such fields out of artifact keys."""
HINT = "hint"
"""Field metadata key: text that ends the message refusing a value of the field (where one is likely meant for
another setting)."""


def yaml_field(*, identity: bool | Callable[[Any], bool] = True, hint: str | None = None) -> Any:
    """A field whose default is in the YAML (as ``FROM_YAML``), with metadata: ``identity=False`` leaves it out of
    artifact keys, a test ``settings -> bool`` leaves it out where the test fails (``IDENTITY``); ``hint`` ends
    the message that refuses a value (``HINT``)."""
    metadata: dict[str, Any] = {IDENTITY: identity}
    if hint:
        metadata[HINT] = hint
    return dataclasses.field(default=FROM_YAML, metadata=metadata)


def _declared_default(value: Any) -> Any:
    """A class attribute's default: a ``dataclasses.field``'s own default, or the attribute itself."""
    return value.default if isinstance(value, dataclasses.Field) else value


def defaults_source(config_class: type) -> str | None:
    """The YAML file that ``config_class`` takes its defaults from (``path`` or ``path#node``); None if none."""
    return config_class.__dict__.get("_yaml_defaults")


def _yaml_values(path: Path, node: str | None, where: str) -> dict[str, Any]:
    if not path.is_file():
        raise TnfError(f"{path}: no such file (a Config takes its defaults from it)")
    try:
        from omegaconf import OmegaConf
    except ImportError:  # a machine with torch and tnf alone (benchmarks): the defaults files are plain YAML
        import yaml

        loaded = yaml.safe_load(path.read_text(encoding="utf-8"))
    else:
        loaded = OmegaConf.to_container(OmegaConf.load(path), resolve=False)
    values = loaded.get(node) if node is not None and isinstance(loaded, dict) else loaded
    if not isinstance(values, dict):
        raise TnfError(f"{where}: expected a mapping of settings, got {values!r}")
    return {str(k): v for k, v in values.items()}


def _section_default(conf: Path, value: str, where: str) -> Any:
    """The default that the interpolation ``value`` of another section's setting (``${touch.radius}``) stands for:
    its value in ``<conf>/<section>/default.yaml``; an environment variable's (``${oc.env:NAME,fallback}``): its
    value when the class is defined, else the fallback. Any other interpolation is an error."""
    from omegaconf import OmegaConf

    if re.fullmatch(r"\$\{oc\.env:[^${}]+\}", value):
        return OmegaConf.create({"v": value}).v
    match = re.fullmatch(r"\$\{(\w+)\.([\w.]+)\}", value)
    path = conf / match[1] / "default.yaml" if match else None
    if match is None or path is None or not path.is_file():
        raise TnfError(f"{where} is an interpolation ({value}); a default must be a value or another section's")
    found = OmegaConf.select(OmegaConf.load(path), match[2], default=_MISSING_KEY)
    if found is _MISSING_KEY or (isinstance(found, str) and "${" in found):
        raise TnfError(f"{where}: {value} names no value in {path}")
    return OmegaConf.to_container(found) if OmegaConf.is_config(found) else found


_MISSING_KEY = object()


def _shareable(value: Any) -> bool:
    """None, a bool, a number, a string or a tuple of them: safe to share between instances."""
    if isinstance(value, tuple):
        return all(_shareable(v) for v in value)
    return value is None or isinstance(value, (bool, int, float, str))
