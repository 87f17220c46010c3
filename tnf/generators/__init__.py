"""Tactile-image generators: the Touch-NeRF cGAN (``tn_cgan``) and the ``lee`` and ``cyclegan`` baselines.

A generator registers in ``tnf.registry.GENERATORS`` (``tnf.generators.base.Generator`` is its interface);
``GeneratorSystem`` trains any of them with Lightning; ``load_generator`` restores one from a checkpoint.
``GeneratorSystem`` and ``load_generator`` import Lightning, so they are imported on first use.
"""

from __future__ import annotations

from typing import Any

from tnf.generators.base import Generator, Optimisation, PlainOptimisation

__all__ = ["Generator", "GeneratorSystem", "Optimisation", "PlainOptimisation", "load_generator"]

_LAZY = {"GeneratorSystem": "tnf.generators.system", "load_generator": "tnf.generators.system"}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'tnf.generators' has no attribute {name!r}")
