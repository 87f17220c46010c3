"""pyproject.toml's optional extras install what their features import."""

from pathlib import Path

import pytest


def _extras() -> dict[str, list[str]]:
    tomllib = pytest.importorskip("tomllib")
    pyproject = tomllib.loads((Path(__file__).resolve().parents[2] / "pyproject.toml").read_text())
    return pyproject["project"]["optional-dependencies"]


def _names(requirements: list[str]) -> set[str]:
    from packaging.requirements import Requirement

    return {Requirement(r).name for r in requirements}


def test_real_extra_installs_taxim_and_jax():
    # taxim: the recordings `tnf calibrate` imports; jax: Taxim's backend in experiments/real_realism.py.
    extras = _extras()
    assert {"taxim", "jax"} <= _names(extras["real"])
    assert "jax" not in _names(extras["test"])  # the test install stays without it
