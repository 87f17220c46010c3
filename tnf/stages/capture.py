"""``tnf capture``: render multi-view RGB-D images of every selected object into the artifact store.

Output per object: ``<data_root>/capture/<source>/<object>/`` (see :mod:`tnf.capture`). Objects already
captured with the same settings are skipped. A source with its own camera images (``objects=captured``) has
them imported instead (:func:`tnf.objects.captured.import_views`).
"""

from __future__ import annotations

from typing import Any

from tnf.artifacts import ArtifactStore
from tnf.capture import capture_config
from tnf.capture.run import capture_objects
from tnf.registry import split_spec
from tnf.stages import data_seed, run_objects, shard_share


def run(cfg: Any) -> list[dict[str, Any]]:
    """Capture the objects of ``cfg`` (cfg.object / cfg.object_names of cfg.objects); returns one row each."""
    from omegaconf import OmegaConf
    from rich.table import Table

    from tnf.runtime import stage_console

    ccfg = capture_config(cfg.capture)
    source, names = run_objects(cfg)
    names = shard_share(names, cfg)  # a job of a sweep over shards: its share
    store = ArtifactStore(cfg.data_root)
    store.clean_partials("capture")
    _, source_params = split_spec(cfg.objects, "objects")
    # Everything that changes the images: the object source's settings, the capture settings, the seed.
    settings = OmegaConf.to_container(cfg.capture, resolve=True)
    config = {"objects": {"name": source.name, **source_params}, "capture": settings, "seed": data_seed(cfg)}
    rows = capture_objects(store, source, names, ccfg, config, data_seed(cfg), bool(cfg.progress))
    table = Table(title=f"capture -> {store.path('capture', source.name)}", header_style="bold")
    for col in ("object", "status", "views", "coverage", "seconds"):
        table.add_column(col)
    for r in rows:
        cov = f"{r['coverage']:.0%}" if "coverage" in r else ""
        table.add_row(r["object"], r["status"], str(r["views"] or ""), cov, f"{r['seconds']:.1f}")
    stage_console().print(table)
    return rows
