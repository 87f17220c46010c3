"""One module per ``tnf`` stage; each exposes ``run(cfg)``, called by the Hydra app in ``tnf.cli``.

The stage layer is the only one that reads a run's config: ``settings`` checks it before any stage works, and
the stages pass plain values to the layers below.
"""

from __future__ import annotations

from typing import Any

from tnf.objects import ObjectSource, select, shard, shard_of


def run_objects(cfg: Any, usable: bool = True) -> tuple[ObjectSource, list[str]]:
    """The object source and object names of a run's ``objects``, ``object_names`` and ``object`` settings;
    ``usable``: less the invalid meshes a source skips (``objects.skip_invalid``), logging why."""
    source, names = select(cfg.objects, cfg.get("object_names"), cfg.get("object"))
    return source, source.usable(names) if usable else names


def data_seed(cfg: Any) -> int:
    """The seed of the data stages (capture, fit-scene, touch, pair): ``data_seed``, else ``seed``. A data item's
    key holds it as its ``seed``."""
    value = cfg.get("data_seed")
    return int(cfg.seed if value is None else value)


def run_shard(cfg: Any) -> tuple[int, int] | None:
    """``(shard, shards)`` of a job in a sweep over object shards, or None (the ``shard`` setting is null)."""
    return shard_of(cfg.get("shard", None), cfg.get("shards", 1))


def shard_share(names: list[str], cfg: Any) -> list[str]:
    """This job's share of ``names`` under the run's ``shard`` and ``shards`` settings (all of them outside a
    sweep over shards)."""
    return shard(names, cfg.get("shard", None), cfg.get("shards", 1))
