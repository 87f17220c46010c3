"""``tnf capture``: render multi-view RGB-D images of every selected object into the artifact store.

Output per object: ``<data_root>/capture/<source>/<object>/`` (see :mod:`tnf.capture`). Objects already
captured with the same settings are skipped. A source with its own camera images (``objects=captured``) has
them imported instead (:func:`tnf.objects.captured.import_views`).
"""

from __future__ import annotations

import logging
import time
from typing import Any

from tnf.errors import TnfError

log = logging.getLogger(__name__)


def run(cfg: Any) -> list[dict[str, Any]]:
    """Capture the objects of ``cfg`` (cfg.object / cfg.object_names of cfg.objects); returns one row each."""
    from concurrent.futures import ThreadPoolExecutor

    import numpy as np
    from rich.console import Console
    from rich.table import Table

    from tnf.artifacts import ArtifactStore
    from tnf.capture import camera_distance, camera_poses, capture_config
    from tnf.capture.render import MeshRenderer, capture_object
    from tnf.objects import select, shard
    from tnf.registry import split_spec
    from tnf.runtime import progress

    ccfg = capture_config(cfg.capture)
    source, names = select(cfg)
    names = shard(names, cfg)  # a job of a sweep over shards: its share
    store = ArtifactStore(cfg.data_root)
    store.clean_partials("capture")
    _, source_params = split_spec(cfg.objects, "objects")
    rows: list[dict[str, Any]] = []
    invalid: list[str] = []  # why each skipped mesh was rejected
    # One renderer for all objects (context and compiled shaders are reused); image files are written by
    # two threads while the next views render.
    renderer: MeshRenderer | None = None
    pool = ThreadPoolExecutor(max_workers=2, thread_name_prefix="capture-write")
    with progress(cfg.progress) as p, pool:
        task = p.add_task(f"capture {source.name}", total=len(names))
        for name in names:
            if source.views(name) is not None:  # the source's own camera images: imported, not rendered
                from tnf.objects.captured import import_views

                rows.append(import_views(store, source, name))
                p.advance(task)
                continue
            item = (source.name, name)
            # Everything that changes the images: the object source's settings, the capture settings, the seed.
            config = {"objects": {"name": source.name, **source_params}, "capture": cfg.capture, "seed": cfg.seed}
            if store.is_done("capture", *item, config=config):
                rows.append({"object": name, "status": "skipped (done)", "views": None, "seconds": 0.0})
                p.advance(task)
                continue
            t0 = time.perf_counter()
            try:
                mesh = source.load(name)
            except TnfError as e:
                if not source.skip_invalid:
                    raise
                log.warning("skipping invalid object %s: %s", name, e)
                invalid.append(str(e))
                mesh = None
            if mesh is None:
                rows.append({"object": name, "status": "skipped (invalid mesh)", "views": 0, "seconds": 0.0})
                p.advance(task)
                continue
            radius = float(np.linalg.norm(mesh.vertices, axis=1).max())
            train, test = camera_poses(radius, ccfg, seed=cfg.seed)
            if renderer is None:
                renderer = MeshRenderer(
                    None,
                    ccfg.resolution,
                    ccfg.resolution,
                    ccfg.background,
                    ccfg.ambient,
                    ccfg.light_intensity,
                    ccfg.antialias,
                )
            renderer.set_mesh(mesh)
            info: dict[str, Any] = {
                "object": name,
                "source": source.name,
                "num_views": len(train),
                "num_test_views": len(test),
                "radius_m": radius,
                "distance_m": camera_distance(radius, ccfg),
                "size_m": [float(x) for x in mesh.extents],
            }
            with store.writing("capture", *item, config=config, info=info) as tmp:
                fill = capture_object(renderer, tmp, train, test, ccfg, pool)
                info["mean_coverage"] = fill  # read when the block ends
            dt = time.perf_counter() - t0
            rows.append(
                {"object": name, "status": "captured", "views": len(train) + len(test), "seconds": dt, "coverage": fill}
            )
            p.advance(task)
    if renderer is not None:
        renderer.close()
    if invalid and len(invalid) == len(names):
        # Skipping broken meshes keeps a long run over many objects going; a run that captured nothing is a failure.
        more = f" (and {len(invalid) - 1} more invalid objects)" if len(invalid) > 1 else ""
        raise TnfError(f"no object captured: {invalid[0]}{more}")
    table = Table(title=f"capture -> {store.path('capture', source.name)}", header_style="bold")
    for col in ("object", "status", "views", "coverage", "seconds"):
        table.add_column(col)
    for r in rows:
        cov = f"{r['coverage']:.0%}" if "coverage" in r else ""
        table.add_row(r["object"], r["status"], str(r["views"] or ""), cov, f"{r['seconds']:.1f}")
    Console(highlight=False).print(table)
    return rows
