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

STAGE_DEFAULTS: dict[str, dict[str, str]] = {"pipeline": {"experiment": "quickstart"}}
"""Config group choices a stage makes unless the command line makes them (``tnf pipeline`` runs the quick start)."""


def stage_choices(stage: str, overrides: Sequence[str]) -> list[str]:
    """The stage's own group choices (``STAGE_DEFAULTS``) for the groups ``overrides`` leave alone."""
    chosen = {o.lstrip("+~").split("=")[0] for o in overrides if not o.startswith("-")}
    own = STAGE_DEFAULTS.get(stage.replace("-", "_"), {})
    return [f"{group}={option}" for group, option in own.items() if group not in chosen]


def stage_overrides(stage: str, overrides: Sequence[str]) -> list[str]:
    """``overrides`` after the stage's own group choices: what composing the stage's config takes."""
    return [*stage_choices(stage, overrides), *overrides]
