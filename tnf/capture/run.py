"""Capture every selected object into the artifact store (``tnf capture``): ``capture/<source>/<object>/``.

A mesh is rendered from the views of ``tnf.capture.camera_poses``; a source with its own camera images has
them imported instead (``tnf.objects.captured.import_views``). Objects already captured with the same settings
are skipped.
"""

from __future__ import annotations

import time
from typing import Any

from tnf.capture import camera_distance, camera_poses
from tnf.capture.render import MeshRenderer, capture_object
from tnf.objects.captured import import_views
from tnf.runtime import progress


def capture_objects(
    store: Any,
    source: Any,
    names: list[str],
    ccfg: Any,
    config: dict[str, Any],
    seed: int,
    show_progress: bool = True,
) -> list[dict[str, Any]]:
    """Capture ``names`` of ``source`` with the settings ``ccfg`` (a ``CaptureConfig``); ``config`` is what
    changes the images (the object source's and capture settings, the seed; its hash decides what is skipped).
    Returns one row per object: status, views, seconds and (captured ones) mean coverage."""
    from concurrent.futures import ThreadPoolExecutor

    rows: list[dict[str, Any]] = []
    # One renderer for all objects (context and compiled shaders are reused); image files are written by
    # two threads while the next views render.
    renderer: list[Any] = []
    pool = ThreadPoolExecutor(max_workers=2, thread_name_prefix="capture-write")
    with progress(show_progress) as p, pool:
        task = p.add_task(f"capture {source.name}", total=len(names))
        for name in names:
            rows.append(_capture_one(store, source, name, ccfg, config, seed, pool, renderer))
            p.advance(task)
    for r in renderer:
        r.close()
    return rows


def _capture_one(
    store: Any,
    source: Any,
    name: str,
    ccfg: Any,
    config: dict[str, Any],
    seed: int,
    pool: Any,
    renderer: list[Any],
) -> dict[str, Any]:
    """Capture (or import, or skip) one object; ``renderer`` holds the shared renderer once made."""
    import numpy as np

    if source.views(name) is not None:  # the source's own camera images: imported, not rendered
        return import_views(store, source, name)
    item = (source.name, name)
    if store.is_done("capture", *item, config=config):
        return {"object": name, "status": "skipped (done)", "views": None, "seconds": 0.0}
    t0 = time.perf_counter()
    mesh = source.load(name)  # the stage's names are usable (ObjectSource.usable): invalid meshes are left out
    radius = float(np.linalg.norm(mesh.vertices, axis=1).max())
    train, test = camera_poses(radius, ccfg, seed=seed)
    if not renderer:
        renderer.append(
            MeshRenderer(
                None,
                ccfg.resolution,
                ccfg.resolution,
                ccfg.background,
                ccfg.ambient,
                ccfg.light_intensity,
                ccfg.antialias,
            )
        )
    renderer[0].set_mesh(mesh)
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
        fill = capture_object(renderer[0], tmp, train, test, ccfg, pool)
        info["mean_coverage"] = fill  # read when the block ends
    dt = time.perf_counter() - t0
    return {"object": name, "status": "captured", "views": len(train) + len(test), "seconds": dt, "coverage": fill}
