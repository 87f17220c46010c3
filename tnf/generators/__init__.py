"""Tactile-image generators: the Touch-NeRF cGAN (``tn_cgan``) and the ``lee`` and ``cyclegan`` baselines.

A generator registers in ``tnf.registry.GENERATORS`` (``tnf.generators.base.Generator`` is its interface);
``GeneratorSystem`` trains any of them with Lightning; ``load_generator`` restores one from a checkpoint.
Every name is imported on first use (they import torch or Lightning), so that the stage settings of
``tnf.generators.settings`` are checked without them.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # pragma: no cover
    from tnf.generators.base import Generator, Optimisation, PlainOptimisation
    from tnf.generators.system import GeneratorSystem, load_generator

__all__ = ["Generator", "GeneratorSystem", "Optimisation", "PlainOptimisation", "load_generator"]

_LAZY = {
    "Generator": "tnf.generators.base",
    "Optimisation": "tnf.generators.base",
    "PlainOptimisation": "tnf.generators.base",
    "GeneratorSystem": "tnf.generators.system",
    "load_generator": "tnf.generators.system",
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'tnf.generators' has no attribute {name!r}")
