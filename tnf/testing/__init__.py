"""Helpers for testing tnf and its plugins: compose a stage's real config, and contract test suites."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

__all__ = [
    "GeneratorContract",
    "ObjectSourceContract",
    "SceneContract",
    "SensorContract",
    "SimulatorContract",
    "compose",
    "random_batch",
    "undocumented_fields",
]

# The contract suites import pytest: load them only when asked for.
_CONTRACTS = {
    "GeneratorContract",
    "ObjectSourceContract",
    "SceneContract",
    "SensorContract",
    "SimulatorContract",
    "random_batch",
    "undocumented_fields",
}


def __getattr__(name: str) -> Any:
    if name in _CONTRACTS:
        from tnf.testing import contracts

        return getattr(contracts, name)
    raise AttributeError(f"module 'tnf.testing' has no attribute {name!r}")


def compose(stage: str, overrides: Sequence[str] = ()) -> Any:
    """Compose the real Hydra config of ``stage`` (e.g. ``"touch"``) with ``overrides``, as ``tnf`` does.

    Plugin config packages registered under ``tnf.conf`` are on the search path, as on the command line.
    """
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from tnf.env import PRIMARY_CONFIG, conf_dir, stage_overrides

    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=conf_dir(), version_base=None):
        return hydra_compose(config_name=PRIMARY_CONFIG, overrides=stage_overrides(stage, overrides))
