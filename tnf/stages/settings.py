"""Checks of the stage sections of a composed config (``touch``, ``train``, ...) before any stage works.

The components (sensors, simulators, scenes, generators, object sources) are validated into their ``Config``
dataclasses by the registry; each stage section (``TYPED``) into its settings dataclass, as its stage does; the
run-wide settings (``TOP_LEVEL``) into :class:`RunSettings`. Every setting is checked against its field's type and
its class's ``validate()``; none by guessing from a default's value.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, cast

from tnf.registry import FROM_YAML, at_least, yaml_defaults, yaml_field
from tnf.runtime import check_memory


@dataclass
@yaml_defaults("base", partial=True)
class RunSettings:
    """The run-wide settings of ``conf/base.yaml`` that are checked before a run: those at the top of the config,
    shared by every stage."""

    seed: int = FROM_YAML
    """Seed for everything random in a run (object split, poses, training); >= 0."""
    data_seed: int | None = FROM_YAML
    """Seed of the data stages (capture, fit-scene, touch, pair); None: ``seed``. >= 0."""
    progress: bool = yaml_field(identity=False)
    """Show progress bars."""
    device: str = yaml_field(identity=False)
    """Where stages compute: ``auto`` (CUDA when available, else the CPU), ``cpu``, ``cuda`` or ``cuda:N``."""
    data_root: str = yaml_field(identity=False)
    """The artifact store's folder: where a run's items live, never what they are."""

    def validate(self) -> None:
        at_least(self, 0, "seed")
        if self.data_seed is not None:
            at_least(self, 0, "data_seed")


TOP_LEVEL = tuple(f.name for f in dataclasses.fields(RunSettings))
"""Run-wide settings checked as :class:`RunSettings` (their defaults are in ``conf/base.yaml``)."""
RUN_ONLY = tuple(f.name for f in dataclasses.fields(RunSettings) if not f.metadata.get("identity", True))
"""Run-wide settings that change how a run goes or where its store lives, never what it makes: no artifact key
holds them (``identity_config``). Their fields say so (``yaml_field(identity=False)``)."""
TYPED = {
    "capture": "tnf.capture.settings:CaptureConfig",
    "fit": "tnf.scenes.settings:FitSettings",
    "touch": "tnf.sim.items:TouchSettings",
    "pair": "tnf.data.settings:PairSettings",
    "train": "tnf.generators.settings:TrainSettings",
    "finetune": "tnf.generators.settings:FinetuneSettings",
    "generate": "tnf.generators.settings:GenerateSettings",
    "evaluate": "tnf.eval.settings:EvaluateSettings",
    "data": "tnf.data.settings:DataSettings",
    "calibrate": "tnf.real.calibrate:CalibrateSettings",
    "pipeline": "tnf.stages.pipeline:PipelineSettings",
}
"""Every stage section and its settings dataclass (``module:class``), which the stage validates it into too."""


def settings_class(section: str) -> type | None:
    """The settings dataclass of ``section`` (``TYPED``), or None for a section that is no stage's."""
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
    """Raise a one-line TnfError naming the first setting of ``cfg`` whose value its settings class refuses: the
    run-wide settings first (``RunSettings``), then each stage section of ``TYPED`` that ``cfg`` has, in that
    order. ``cfg`` is a composed config or a mapping holding some of its sections."""
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    from tnf.registry import from_dict

    def value(key: str) -> Any:
        try:
            node = cfg[key]
            return OmegaConf.to_container(node, resolve=True) if OmegaConf.is_config(node) else node
        except OmegaConfBaseException:  # an interpolation only a running Hydra job resolves: left to the stage
            return _UNRESOLVED

    run_wide = {k: value(k) for k in TOP_LEVEL if k in cfg}
    from_dict(RunSettings, {k: v for k, v in run_wide.items() if v is not _UNRESOLVED}, where="")
    for key in TYPED:
        if key not in cfg:
            continue
        section = value(key)
        cls = settings_class(key)
        if section is not _UNRESOLVED and cls is not None:
            from_dict(cls, section, where=key)


_UNRESOLVED = object()

# The component groups whose settings a stage's command line is checked for before any work: those it builds
# late (the pipeline trains after hours of data stages; a sweep's first jobs run before a later job's values).
STAGE_COMPONENTS = {
    "pipeline": ("objects", "scene", "sensor", "simulator", "generator"),
    "train": ("generator",),
    "generate": ("generator",),
    "evaluate": ("generator",),
}


def check_components(cfg: Any, stage: str) -> None:
    """Raise a one-line TnfError for the first component section of ``cfg`` (``generator``, ``scene``, ...) that
    ``stage`` builds (``STAGE_COMPONENTS``) whose values its component's Config refuses (``generator.ngf=0``)."""
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    from tnf.registry import REGISTRIES, split_spec

    for kind in STAGE_COMPONENTS.get(stage, ()):
        if kind not in cfg:
            continue
        try:
            spec = OmegaConf.to_container(cfg[kind], resolve=True)
        except OmegaConfBaseException:  # an interpolation only a running Hydra job resolves: left to the stage
            continue
        name, params = split_spec(cast(Any, spec), kind)  # a mapping or a name; split_spec checks which
        REGISTRIES[kind].config(name, params)


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
    rays, together = get("fit", "batch_rays"), get("fit", "batch_objects") or 1
    if rays and (every or stage == "fit_scene"):
        what = "fitting a scene" if together == 1 else f"fitting {together} scenes together"
        settings = f"fit.batch_rays={rays}" + (f", fit.batch_objects={together}" if together > 1 else "")
        out.append((rays * together * _RAY_BYTES, what, settings))
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
