"""Process-wide settings that must be in place before heavy libraries are imported."""

from __future__ import annotations

import os


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
