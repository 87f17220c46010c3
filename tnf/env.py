"""Process-wide settings that must be in place before heavy libraries are imported."""

from __future__ import annotations

import os
from collections.abc import Sequence


def headless_rendering() -> None:
    """Make OpenGL render without a display: EGL (Mesa on a CPU, the driver on an NVIDIA GPU).

    Called before pyrender / PyOpenGL are imported; respects values the user set.
    """
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    os.environ.setdefault("PYGLET_HEADLESS", "true")


def conf_dir() -> str:
    """The folder of tnf's Hydra configs.

    In an installed wheel they ship inside the package (``tnf/conf``); in a checkout or an editable
    install they are the repository's top-level ``conf/``.
    """
    here = os.path.dirname(os.path.abspath(__file__))
    packaged = os.path.join(here, "conf")
    if os.path.isdir(packaged):
        return packaged
    return os.path.join(os.path.dirname(here), "conf")


PRIMARY_CONFIG = "tnf"
"""The primary config that every stage composes (``conf/tnf.yaml``)."""

STAGE_CHOICES = "stage_choices.yaml"
"""The file in ``conf_dir()`` of the config group choices each stage makes unless the command line makes them:
``{stage: {group: option}}`` (``conf/stage_choices.yaml``)."""


def stage_defaults(stage: str) -> dict[str, str]:
    """The config group choices ``stage`` makes unless the command line makes them (``STAGE_CHOICES``)."""
    import yaml

    with open(os.path.join(conf_dir(), STAGE_CHOICES)) as f:
        choices = yaml.safe_load(f) or {}
    return {str(group): str(option) for group, option in (choices.get(stage.replace("-", "_")) or {}).items()}


def stage_choices(stage: str, overrides: Sequence[str]) -> list[str]:
    """The stage's own group choices (``stage_defaults``) for the groups ``overrides`` leave alone."""
    chosen = {o.lstrip("+~").split("=")[0] for o in overrides if not o.startswith("-")}
    return [f"{group}={option}" for group, option in stage_defaults(stage).items() if group not in chosen]


def stage_overrides(stage: str, overrides: Sequence[str]) -> list[str]:
    """``overrides`` after the stage's own group choices: what composing the stage's config takes."""
    return [*stage_choices(stage, overrides), *overrides]
