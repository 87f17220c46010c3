"""Registries: one per kind of component, filled from entry points, tnf's own components included.

Every component, in-tree or from a plugin, is a class with a nested ``Config`` dataclass, registered
through an entry point in its kind's group. tnf lists its own in its ``pyproject.toml``, exactly as a
third-party package does::

    [project.entry-points."tnf.sensors"]
    digit = "tnf.sensors.digit:Digit"

The entry-point name is the registry name. Entry points live in the installed package metadata, so tnf
must be installed (``pip install -e .`` in a checkout), and reinstalled after its entry points change.

Discovery is lazy: the entry points of a kind are imported at the first lookup in that kind's registry,
never at ``import tnf``. A plugin whose import fails is a one-line error naming its entry point.

A ``Config`` takes its defaults from the component's YAML option (``yaml_defaults``): each default is written
once, in the file that users read and override, and each field says so with ``= FROM_YAML``. That machinery
(``from_dict``, ``yaml_defaults``, ``yaml_field``, ...) lives in ``tnf.settings`` and is re-exported here.
"""

from __future__ import annotations

import dataclasses
import importlib
import importlib.metadata as md
import sys
import threading
from collections.abc import Mapping
from typing import Any

from tnf.errors import TnfError
from tnf.settings import (
    FROM_YAML,
    HINT,
    IDENTITY,
    SettingError,
    at_least,
    defaults_source,
    from_dict,
    plain,
    yaml_defaults,
    yaml_field,
)

# The settings machinery (tnf.settings) is part of the registry's API: components import it from here.
__all__ = [
    "FROM_YAML",
    "GENERATORS",
    "HINT",
    "IDENTITY",
    "IN_TREE",
    "OBJECTS",
    "REGISTRIES",
    "SCENES",
    "SENSORS",
    "SIMULATORS",
    "Entry",
    "Registry",
    "SettingError",
    "at_least",
    "config_to_dict",
    "defaults_source",
    "from_dict",
    "split_spec",
    "yaml_defaults",
    "yaml_field",
]

IN_TREE = "tnf"  # the distribution name of tnf itself


@dataclasses.dataclass(frozen=True)
class Entry:
    """A registered component: its name, the object (usually a class) and where it comes from."""

    name: str
    obj: Any
    origin: str  # the distribution the entry point comes from ("tnf" for in-tree components)

    @property
    def config_class(self) -> type | None:
        return getattr(self.obj, "Config", None)


class Registry:
    """A flat name -> component table for one kind of component.

    Args:
        kind: what the components are ("sensor", "scene", ...), used in messages.
        group: the entry-point group that registers components of this kind ("tnf.sensors", ...).
        in_tree: tnf itself registers components of this kind; discovery fails with a one-line error when
            tnf's package metadata lists none (tnf not installed, or installed from an older checkout).
        base: ``"module:Class"``, the base class every entry point's class must subclass (named, not imported,
            so that this module stays below the components' layers); None checks nothing.
        required: methods of ``base`` a subclass must override (the base's only raise NotImplementedError),
            ``"a|b"`` for either of two; an abstract base's abstract methods are checked as well.
    """

    def __init__(
        self, kind: str, group: str, in_tree: bool = False, base: str | None = None, required: tuple[str, ...] = ()
    ):
        self.kind = kind
        self.group = group
        self.in_tree = in_tree
        self.base = base
        self.required = required
        self._entries: dict[str, Entry] = {}
        self._from_entry_points: set[str] = set()
        self._discovered = False
        self._lock = threading.RLock()

    # -- registration -------------------------------------------------------------------------------
    def add(self, name: str, obj: Any, origin: str) -> None:
        """Register ``obj`` under ``name`` (entry points do this; tests add stand-ins directly).

        A second, different object under the same name is an error naming both.
        """
        if not isinstance(name, str) or not name:
            raise TnfError(f"{self.kind} registry: a component name must be a non-empty string, got {name!r}")
        with self._lock:
            old = self._entries.get(name)
            if old is not None:
                if old.obj is obj:
                    return
                raise TnfError(
                    f"duplicate {self.kind} {name!r}: registered by {_where(old.obj, old.origin)} "
                    f"and again by {_where(obj, origin)}"
                )
            self._entries[name] = Entry(name, obj, origin)

    # -- discovery ----------------------------------------------------------------------------------
    def _discover(self) -> None:
        with self._lock:
            if self._discovered:
                return
            # tnf's own entry points first, so that a clash names the in-tree component first.
            eps = sorted(md.entry_points(group=self.group), key=lambda ep: _dist_name(ep) != IN_TREE)
            if self.in_tree and not any(_dist_name(ep) == IN_TREE for ep in eps):
                raise TnfError(_no_metadata(self.kind, self.group))
            # Mark first: a component's module may look up this registry while we import it.
            self._discovered = True
            try:
                for ep in eps:
                    obj = _load(ep, self.kind)
                    self._check_contract(ep.name, obj, _dist_name(ep))
                    self.add(ep.name, obj, origin=_dist_name(ep))
                    self._from_entry_points.add(ep.name)
            except BaseException:
                self._discovered = False
                raise

    def _check_contract(self, name: str, obj: Any, origin: str) -> None:
        """A one-line TnfError when entry point ``name``'s object is not a subclass of ``base``, or leaves one of
        its ``required`` (or abstract) methods unimplemented."""
        if self.base is None:
            return
        module, _, attr = self.base.partition(":")
        base = getattr(importlib.import_module(module), attr)
        where = f"{self.kind} {name!r} ({_where(obj, origin)})"
        if not (isinstance(obj, type) and issubclass(obj, base)):
            raise TnfError(f"{where} is not a subclass of {module}.{attr}; subclass it (docs/plugins.md)")
        missing = [
            m.replace("|", " (or ") + ")" * ("|" in m)
            for m in self.required
            if all(getattr(obj, a, None) is getattr(base, a, None) for a in m.split("|"))
        ]
        missing += sorted(set(getattr(obj, "__abstractmethods__", ())) - set(missing))
        if missing:
            raise TnfError(f"{where} does not implement {', '.join(missing)} of {module}.{attr} (docs/plugins.md)")

    def refresh(self) -> None:
        """Forget what entry points registered and discover again (after installing a plugin in a running process)."""
        with self._lock:
            self._entries = {k: e for k, e in self._entries.items() if k not in self._from_entry_points}
            self._from_entry_points.clear()
            self._discovered = False

    # -- lookup -------------------------------------------------------------------------------------
    def entries(self) -> list[Entry]:
        self._discover()
        return sorted(self._entries.values(), key=lambda e: e.name)

    def names(self) -> list[str]:
        return [e.name for e in self.entries()]

    def __contains__(self, name: object) -> bool:
        self._discover()
        return name in self._entries

    def entry(self, name: str) -> Entry:
        self._discover()
        try:
            return self._entries[name]
        except KeyError:
            available = ", ".join(sorted(self._entries)) or "none"
            raise TnfError(f"unknown {self.kind} {name!r}; available: {available}") from None

    def get(self, name: str) -> Any:
        return self.entry(name).obj

    def config(self, name: str, params: Mapping[str, Any] | None = None) -> Any:
        """Validate ``params`` into the component's ``Config`` dataclass (defaults fill missing keys)."""
        entry = self.entry(name)
        cls = entry.config_class
        if cls is None or not dataclasses.is_dataclass(cls):
            raise TnfError(f"{self.kind} {name!r} ({_where(entry.obj, entry.origin)}) declares no Config dataclass")
        return from_dict(cls, dict(params or {}), where=f"{self.kind}.{name}")

    def build(self, spec: Mapping[str, Any] | str, **kwargs: Any) -> Any:
        """Build a component from ``{"name": ..., <config fields>...}`` or from a bare name.

        The component's constructor receives the validated Config as its first argument.
        """
        name, params = split_spec(spec, self.kind)
        cfg = self.config(name, params)
        entry = self.entry(name)
        try:
            return entry.obj(cfg, **kwargs)
        except TnfError:
            raise
        except Exception as e:  # a plugin's own failure: one line naming it (tnf's own keep their traceback)
            if entry.origin == IN_TREE:
                raise
            first = (str(e).splitlines() or [""])[0][:300]
            raise TnfError(
                f"{self.kind} {name!r} ({_where(entry.obj, entry.origin)}) failed to build: {type(e).__name__}: "
                f"{first} (HYDRA_FULL_ERROR=1 shows the traceback)"
            ) from e


def split_spec(spec: Mapping[str, Any] | str, kind: str = "component") -> tuple[str, dict[str, Any]]:
    """``{"name": n, **params}`` (a Hydra group node) or ``"n"`` -> ``(n, params)``."""
    if isinstance(spec, str):
        return spec, {}
    params = plain(spec)
    if not isinstance(params, dict):
        raise TnfError(f"a {kind} config needs a 'name' key, got {params!r}")
    if "name" not in params:
        raise TnfError(f"a {kind} config needs a 'name' key: its registry name (`name: NAME` first in its YAML)")
    name = params.pop("name")
    return name, params


def config_to_dict(cfg: Any) -> dict[str, Any]:
    """A Config dataclass as plain JSON-friendly data (tuples become lists)."""
    return plain(dataclasses.asdict(cfg))


def _dist_name(ep: md.EntryPoint) -> str:
    return ep.dist.name if ep.dist is not None else "unknown distribution"


def _load(ep: md.EntryPoint, kind: str) -> Any:
    """The object entry point ``ep`` names; a TnfError naming the entry point and its distribution when its import
    fails (the import's own TnfError, one line already, passes unchanged)."""
    try:
        return ep.load()
    except TnfError:
        raise
    except Exception as e:
        dist = _dist_name(ep)
        missing = e.name if isinstance(e, ModuleNotFoundError) else None
        loaded = sys.modules.get(ep.module)
        if missing and (ep.module == missing or ep.module.startswith(f"{missing}.")):
            fix = f"fix the entry point in {dist}'s pyproject.toml and reinstall it"  # no such module
        elif missing:
            fix = f"install {missing!r}: {dist} imports it"
        elif isinstance(e, AttributeError) and loaded is not None and not hasattr(loaded, ep.attr.split(".")[0]):
            fix = f"fix the entry point in {dist}'s pyproject.toml and reinstall it"  # no such class
        else:
            fix = f"an error in {dist}'s code (`tnf --verbose` shows where)"
        raise TnfError(
            f"{kind} {ep.name!r} ({ep.group} entry point {ep.value!r} of {dist}) cannot be loaded: "
            f"{type(e).__name__}: {e}; {fix}"
        ) from e


def _no_metadata(kind: str, group: str) -> str:
    try:
        md.distribution(IN_TREE)
    except md.PackageNotFoundError:
        return (
            f"no {kind} found: tnf's package metadata is missing (a source tree that was never installed?); "
            "run `pip install -e .` in the checkout"
        )
    return (
        f"no {kind} found: tnf's installed metadata lists no {group!r} entry points (installed from an older "
        "checkout?); run `pip install -e .` in the checkout again"
    )


def _where(obj: Any, origin: str) -> str:
    mod = getattr(obj, "__module__", "?")
    qual = getattr(obj, "__qualname__", type(obj).__name__)
    return f"{mod}.{qual} (from {origin})"


# -- the registries ---------------------------------------------------------------------------------
# tnf's own components are entry points in pyproject.toml, like a plugin's.
OBJECTS = Registry(
    "objects", "tnf.objects", in_tree=True, base="tnf.objects:ObjectSource", required=("names", "_load|load")
)
SCENES = Registry("scene", "tnf.scenes", in_tree=True, base="tnf.scenes.base:Scene", required=("render_rgbd",))
SENSORS = Registry("sensor", "tnf.sensors", in_tree=True, base="tnf.sensors:Sensor")
SIMULATORS = Registry("simulator", "tnf.simulators", in_tree=True, base="tnf.sim.base:Simulator")
GENERATORS = Registry(
    "generator",
    "tnf.generators",
    in_tree=True,
    base="tnf.generators:Generator",
    required=("generate", "training_step", "configure_optimizers"),
)

REGISTRIES: dict[str, Registry] = {r.kind: r for r in (OBJECTS, SCENES, SENSORS, SIMULATORS, GENERATORS)}
