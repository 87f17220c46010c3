"""Checks of the stage sections of a composed config (``touch``, ``train``, ...) before any stage works.

The components (sensors, simulators, scenes, generators, object sources) are validated into their ``Config``
dataclasses by the registry, and the sections of ``TYPED`` into their settings dataclasses, as their stages do.
The other sections are plain YAML; their defaults (``conf/<section>/default.yaml``) are the schema: a setting
whose default is an integer takes an integer (not ``1.5``, not ``"abc"``), and a non-negative one (a count, a size,
a number of epochs) stays non-negative; a number takes a finite number; a switch takes true or false; a list
takes a list. Settings whose default is null take anything.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from tnf.env import conf_dir
from tnf.errors import TnfError
from tnf.runtime import check_memory

SECTIONS = (
    "capture",
    "fit",
    "touch",
    "pair",
    "train",
    "finetune",
    "generate",
    "evaluate",
    "data",
    "calibrate",
    "pipeline",
)
"""Config sections with a ``default.yaml`` that sets every key's type."""
TOP_LEVEL = ("seed", "progress")
"""Run-wide settings; their defaults in ``conf/base.yaml`` set their types."""


@functools.lru_cache(maxsize=1)
def schema() -> dict[str, Any]:
    """``{section: defaults}`` from ``conf/<section>/default.yaml``, plus the run-wide settings (``conf/base.yaml``)."""
    from omegaconf import OmegaConf

    base = OmegaConf.to_container(OmegaConf.load(Path(conf_dir()) / "base.yaml"), resolve=False)
    assert isinstance(base, dict)
    out: dict[str, Any] = {k: base[k] for k in TOP_LEVEL}
    for section in SECTIONS:
        path = Path(conf_dir()) / section / "default.yaml"
        if path.is_file():
            out[section] = OmegaConf.to_container(OmegaConf.load(path), resolve=False)
    return out


RUN_ONLY = ("progress", "device", "data_root")
"""Run-wide settings that change how a run goes or where its store lives, never what it makes: no artifact key
holds them (``identity_config``)."""
TYPED = {
    "touch": "tnf.sim.items:TouchSettings",
    "pair": "tnf.data.settings:PairSettings",
    "data": "tnf.data.settings:DataSettings",
    "train": "tnf.generators.settings:TrainSettings",
    "finetune": "tnf.generators.settings:FinetuneSettings",
    "generate": "tnf.generators.settings:GenerateSettings",
    "evaluate": "tnf.eval.settings:EvaluateSettings",
    "calibrate": "tnf.real.calibrate:CalibrateSettings",
}
"""The sections validated into their settings dataclass (``module:class``), as the stage itself does."""


def settings_class(section: str) -> type | None:
    """The settings dataclass of ``section`` (``TYPED``), or None for a section checked by its defaults' types."""
    import importlib

    if section not in TYPED:
        return None
    module, _, name = TYPED[section].partition(":")
    cls: type = getattr(importlib.import_module(module), name)
    return cls


def identity_config(cfg: Any) -> dict[str, Any]:
    """The whole config as an artifact key records it: each typed section as its settings (``tnf.artifacts.identity``
    leaves out what does not make the artifact), the simulator by ``simulator_key``, the other sections and
    run-wide settings as plain data, without ``RUN_ONLY``."""
    from omegaconf import OmegaConf

    from tnf.registry import from_dict
    from tnf.sim.base import simulator_key

    plain = OmegaConf.to_container(cfg, resolve=True) if OmegaConf.is_config(cfg) else dict(cfg)
    assert isinstance(plain, dict)
    out: dict[str, Any] = {}
    for key, value in plain.items():
        if key in RUN_ONLY:
            continue
        cls = settings_class(str(key))
        if cls is not None:
            value = from_dict(cls, value, where=str(key))
        elif key == "simulator" and value is not None:
            value = simulator_key(value)
        out[str(key)] = value
    return out


def check_settings(cfg: Any) -> None:
    """Raise a one-line TnfError naming the first setting of ``cfg`` whose value does not fit its default's type."""
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    from tnf.registry import from_dict

    for key, default in schema().items():
        if key not in cfg:
            continue
        value = cfg[key]
        if OmegaConf.is_config(value):
            try:
                value = OmegaConf.to_container(value, resolve=True)
            except OmegaConfBaseException:  # an interpolation only a running Hydra job resolves: left to the stage
                continue
        cls = settings_class(key)
        if cls is not None:
            from_dict(cls, value, where=key)
        else:
            _check(value, default, key)


def _check(value: Any, default: Any, where: str) -> None:
    if default is None or (isinstance(default, str) and default.startswith("${")):
        return  # anything goes, or an interpolation whose type the default does not show
    if isinstance(default, Mapping):
        if value is None:
            return
        if not isinstance(value, Mapping):
            raise TnfError(f"{where}: expected a section of settings, got {value!r}")
        for k, d in default.items():
            if k in value:
                _check(value[k], d, f"{where}.{k}")
        return
    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise TnfError(f"{where}: expected true or false, got {value!r}")
    elif isinstance(default, int):
        if isinstance(value, bool) or not isinstance(value, int):
            raise TnfError(f"{where}: expected a whole number, got {value!r}")
        if default >= 0 > value:
            raise TnfError(f"{where}: must be >= 0, got {value}")
    elif isinstance(default, float):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise TnfError(f"{where}: expected a number, got {value!r}")
        if not math.isfinite(value):
            raise TnfError(f"{where}: expected a finite number, got {value!r}")
    elif isinstance(default, list):
        if value is not None and not isinstance(value, list):
            raise TnfError(f"{where}: expected a list, got {value!r}")


# Bytes that one unit of each size setting needs at the least (a lower bound: a refusal is never wrong).
_RAY_BYTES = 128  # a fitting ray: origin, direction, target colour, index and at least one sample's features
_PAIR_PIXEL_BYTES = 16  # a rendered RGB-D pixel as float32
_IMAGE_BYTES = 128 * 128 * 10 * 4 * 2  # a 128 px training pair (RGB, depth, background, tactile) and its gradient


def size_demands(cfg: Any, stage: str) -> list[tuple[float, str, str]]:
    """``(bytes at least, what, settings)`` for the size settings that ``stage`` (or the pipeline) allocates by."""
    every = stage == "pipeline"

    def get(section: str, key: str) -> Any:
        node = cfg.get(section) if hasattr(cfg, "get") else None
        value = node.get(key) if node is not None and hasattr(node, "get") else None
        return value if isinstance(value, int) and not isinstance(value, bool) else None

    out: list[tuple[float, str, str]] = []
    rays = get("fit", "batch_rays")
    if rays and (every or stage == "fit_scene"):
        out.append((rays * _RAY_BYTES, "fitting a scene", f"fit.batch_rays={rays}"))
    batch, px = get("pair", "render_batch"), get("pair", "render_px")
    if batch and px and (every or stage == "pair"):
        out.append(
            (batch * px * px * _PAIR_PIXEL_BYTES, "rendering pairs", f"pair.render_batch={batch}, pair.render_px={px}")
        )
    b = get("data", "batch_size")
    if b and (every or stage in ("train", "finetune")):
        out.append((b * _IMAGE_BYTES, "a training batch", f"data.batch_size={b}"))
    g = get("generate", "batch_size")
    if g and (every or stage == "generate"):
        out.append((g * _IMAGE_BYTES / 2, "a generation batch", f"generate.batch_size={g}"))
    return out


def check_sizes(cfg: Any, stage: str) -> None:
    """Refuse (one line) a size setting whose least memory is over what the machine has available."""

    for need, what, settings in size_demands(cfg, stage.replace("-", "_")):
        check_memory(need, what, settings)
