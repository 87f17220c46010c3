"""Compose a stage's real Hydra config, as the ``tnf`` command does."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from tnf.env import PRIMARY_CONFIG, conf_dir, stage_overrides


def compose(stage: str, overrides: Sequence[str] = ()) -> Any:
    """Compose the real Hydra config of ``stage`` (e.g. ``"touch"``) with ``overrides``, as ``tnf`` does.

    Plugin config packages registered under ``tnf.conf`` are on the search path, as on the command line.
    """
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=conf_dir(), version_base=None):
        return hydra_compose(config_name=PRIMARY_CONFIG, overrides=stage_overrides(stage, overrides))
