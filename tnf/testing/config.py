"""Compose a stage's real Hydra config, as the ``tnf`` command does."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator, Sequence
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


@contextlib.contextmanager
def hydra_job(stage: str, overrides: Sequence[str] = ()) -> Iterator[Any]:
    """Compose the stage's config as ``compose`` does, with Hydra's runtime set for the block as in a ``tnf`` job
    (``hydra.runtime.choices``: the config options chosen, which run ids name; ``tnf.generators.names``)."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra
    from hydra.core.hydra_config import HydraConfig
    from omegaconf import open_dict

    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=conf_dir(), version_base=None):
        cfg = hydra_compose(
            config_name=PRIMARY_CONFIG, overrides=stage_overrides(stage, overrides), return_hydra_config=True
        )
    earlier = HydraConfig.instance().cfg
    HydraConfig.instance().set_config(cfg)
    with open_dict(cfg):
        del cfg["hydra"]
    try:
        yield cfg
    finally:
        HydraConfig.instance().cfg = earlier
