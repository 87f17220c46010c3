"""Helpers for testing tnf and its plugins: compose a stage's real config (``hydra_job``: with Hydra's runtime, as
in a ``tnf`` job), and contract test suites."""

from __future__ import annotations

from typing import Any

from tnf.testing.config import compose, hydra_job

__all__ = [
    "GeneratorContract",
    "ObjectSourceContract",
    "SceneContract",
    "SensorContract",
    "SimulatorContract",
    "compose",
    "hydra_job",
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
