"""``tnf touch``: simulate tactile touches of each selected object with the configured sensor.

Writes ``<data_root>/touch/<sensor>/<source>/<object>/``: ``images/00000.png``..., ``background.png`` and a
manifest whose info lists every touch (split, start and contact poses, contact point, force, penetration).
Finished items are skipped; ``-m sensor=digit,omnitact`` runs several sensors, ``-m shards=N 'shard=range(N)'``
splits the objects over N jobs (docs/cluster.md).
"""

from __future__ import annotations

import contextlib
import zlib
from collections.abc import Iterator
from concurrent.futures import wait
from typing import Any

SPLITS = ("train", "val", "novel_view")


def item_config(cfg: Any, sensor: Any) -> dict[str, Any]:
    """What decides a touch item's content (its hash decides whether a finished item is reused)."""
    from omegaconf import OmegaConf

    from tnf.registry import split_spec

    touch = OmegaConf.to_container(cfg.touch, resolve=True)
    assert isinstance(touch, dict)
    if touch.get("force_range") is None:  # fixed-force items keep the hash they had before force ranges existed
        touch.pop("force_range", None)
    return {
        "sensor": sensor.describe(),
        "simulator": split_spec(cfg.simulator, "simulator"),
        "touch": touch,
        "seed": int(cfg.seed),
    }


def _png(image: Any, level: int = 6) -> bytes:
    import io

    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(image).save(buf, format="PNG", compress_level=level)
    return buf.getvalue()


def _write_png(path: Any, image: Any) -> None:
    """Write one tactile image as a PNG. Level 1: noisy sensor images barely compress further, and level 6 costs
    3.5x the time (35 ms per 240x320 Digit frame on one core, more than simulating it)."""
    path.write_bytes(_png(image, level=1))


@contextlib.contextmanager
def _settled(writes: list[Any]) -> Iterator[None]:
    """On an exception (a failed write, a full disk, Ctrl-C), cancel the image writes not started and wait for the
    running ones, so that none writes into the item's temporary folder while it is being removed."""
    try:
        yield
    except BaseException:
        for w in writes:
            w.cancel()
        wait(writes)
        raise


def run(cfg: Any) -> None:
    import os
    from concurrent.futures import ThreadPoolExecutor

    import numpy as np
    from rich.console import Console

    from tnf.artifacts import ArtifactStore, require_space
    from tnf.errors import TnfError
    from tnf.objects import select, shard, shard_of
    from tnf.registry import SENSORS, SIMULATORS
    from tnf.runtime import job_device, progress, resolve_device, warp_device
    from tnf.sim.forces import force_plan, force_sampler
    from tnf.sim.touch import collect

    console = Console(highlight=False)
    tc = cfg.touch
    store = ArtifactStore(cfg.data_root)
    sensor = SENSORS.build(cfg.sensor)
    sensor.check_force(float(tc.force))
    plan = force_plan(tc.get("force_range"), sensor)  # None: every touch presses with touch.force
    if tc.radius <= 0:
        raise TnfError(f"touch.radius must be > 0 metres, got {tc.radius}")
    source, names = select(cfg)
    names = shard(names, cfg)  # a job of a sweep over shards: its share
    if any(source.touches(n) is not None for n in names):  # the source's own tactile frames: imported, not simulated
        from tnf.objects.captured import import_touches

        for n in names:
            console.print(import_touches(store, sensor, source, n, start_radius=float(tc.radius)))
        return
    config = item_config(cfg, sensor)
    todo = [n for n in names if not store.is_done("touch", sensor.name, source.name, n, config=config)]
    for n in names:
        if n not in todo:
            console.print(f"touch {sensor.name}/{source.name}/{n}: done, skipped")
    if not todo:
        return
    part = shard_of(cfg)
    device = warp_device(job_device(resolve_device(cfg.device), part))
    sim = SIMULATORS.build(cfg.simulator, sensor=sensor, device=device)
    counts = {"train": int(tc.n_touches), "val": int(tc.n_val), "novel_view": int(tc.n_novel_view)}
    # What an item takes on disk, at least: its background, and each touch about the size of the background at the
    # touches' compression (a touch adds contact shading to it, so it compresses a little worse: ~1.3x measured).
    background_png = _png(sim.background)
    n_images = sum(counts.values())
    item_bytes = len(background_png) + n_images * len(_png(sim.background, level=1))
    # PNG encoding releases the GIL: a pool writes images while the simulator runs the next split.
    with progress(cfg.progress) as bar, ThreadPoolExecutor(max(1, min(16, os.cpu_count() or 1))) as pool:
        task = bar.add_task("touch", total=len(todo) * sum(counts.values()))
        for name in todo:
            mesh = source.load(name)
            seed = (int(cfg.seed) * 1_000_003 + zlib.crc32(f"{source.name}/{name}".encode())) % 2**31
            rng = np.random.default_rng(seed)
            touches: list[dict[str, Any]] = []
            discarded = {}
            item = ("touch", sensor.name, source.name, name)
            info: dict[str, Any] = {}
            writes: list[Any] = []
            what = f"touch item {store.path(*item)} ({n_images} images of {sensor.width}x{sensor.height})"
            require_space(store.path(*item), item_bytes, what)  # before simulating what could not be stored
            with store.writing(*item, config=config, info=info) as tmp, _settled(writes):
                (tmp / "images").mkdir()
                (tmp / "background.png").write_bytes(background_png)
                for split_no, split in enumerate(SPLITS):
                    if counts[split] == 0:
                        discarded[split] = 0
                        continue
                    force = float(tc.force) if plan is None else force_sampler(plan, split, seed + split_no)
                    got = collect(
                        sim, mesh, counts[split], rng,
                        radius=float(tc.radius), force=force, batch_size=int(tc.batch_size),
                        axis=list(tc.novel_view_axis), cone_deg=float(tc.novel_view_cone),
                        inside=split == "novel_view", up=list(tc.up), random_roll=bool(tc.random_roll),
                        seed=seed + split_no, max_attempts=int(tc.max_attempts),
                    )  # fmt: skip
                    discarded[split] = got.discarded
                    r = got.results
                    for i in range(len(r.images)):
                        index = len(touches)
                        rel = f"images/{index:05d}.png"
                        writes.append(pool.submit(_write_png, tmp / rel, r.images[i]))
                        touches.append(
                            {
                                "index": index,
                                "split": split,
                                "image": rel,
                                "start_c2w": got.start_c2w[i].tolist(),
                                "contact_c2w": r.contact_c2w[i].tolist(),
                                "contact_point": r.contact_point[i].astype(float).tolist(),
                                "force": float(r.force[i]),
                                "penetration": float(r.penetration[i]),
                            }
                        )
                        if got.target_force is not None and plan is not None:
                            target = float(got.target_force[i])
                            touches[-1]["force_target"] = target
                            touches[-1]["force_band"] = plan.band_of([target])[0]
                        bar.advance(task)
                for w in writes:
                    w.result()  # every image is on disk (or its error raised) before the item is finalised
                info.update(
                    {
                        "sensor": sensor.describe(),
                        "object": name,
                        "source": source.name,
                        "touches": touches,
                        "counts": {**{s: counts[s] for s in SPLITS}, "discarded": discarded},
                        "width": sensor.width,
                        "height": sensor.height,
                        "intrinsics": list(sensor.intrinsics()),
                    }
                )
                if plan is not None:
                    info["force_range"] = plan.describe()
            n_disc = sum(discarded.values())
            console.print(f"touch {sensor.name}/{source.name}/{name}: {len(touches)} touches, {n_disc} discarded")
