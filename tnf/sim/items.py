"""Simulated touch items on disk (``tnf touch``): ``touch/<sensor>/<source>/<object>/``.

An item holds ``images/00000.png``..., ``background.png`` and a manifest whose info lists every touch (split,
start and contact poses, contact point, force, penetration).
"""

from __future__ import annotations

import contextlib
import zlib
from collections.abc import Iterator
from concurrent.futures import wait
from dataclasses import dataclass
from typing import Any

from tnf.artifacts import require_space
from tnf.registry import FROM_YAML, SIMULATORS, SettingError, at_least, yaml_defaults, yaml_field
from tnf.runtime import progress
from tnf.sim.forces import force_sampler
from tnf.sim.touch import collect
from tnf.touches import TouchRecord, as_matrix, as_point

SPLITS = ("train", "val", "novel_view")


@dataclass
@yaml_defaults("touch/default")
class TouchSettings:
    """The ``touch`` section: where the sensor starts, how hard it presses, how many touches."""

    n_touches: int = FROM_YAML
    """Training touches per object (touches without contact do not count)."""
    n_val: int = FROM_YAML
    """Validation touches per object, from the same pose distribution as training."""
    n_novel_view: int = FROM_YAML
    """Touches per object from the held-out cone of start directions (novel viewpoints)."""
    radius: float = FROM_YAML
    """Distance of the start poses from the object centre, metres (the sensor starts outside the object)."""
    force: float = FROM_YAML
    """Target normal force of every press, newtons (within the sensor's force range)."""
    force_range: dict[str, Any] | None = FROM_YAML
    """Touches at many forces (docs/force.md): null presses every touch with ``force``; a section ``{min, max,
    dist, interpolation, extrapolation}`` (newtons; ``tnf.sim.forces.force_plan`` checks it against the sensor)
    draws each touch's force."""
    batch_size: int = FROM_YAML
    """Touches simulated in one launch (it sets the noise seed of each launch: part of an item's identity)."""
    random_roll: bool = FROM_YAML
    """Rotate each sensor randomly about its view axis; false: the roll is fixed by ``up``."""
    up: tuple[float, float, float] = FROM_YAML
    """World up vector that fixes the sensor's roll (image +y toward it)."""
    novel_view_axis: tuple[float, float, float] = FROM_YAML
    """Centre direction of the held-out cone of start directions."""
    novel_view_cone: float = FROM_YAML
    """Half-angle of the held-out cone, degrees (training and validation starts lie outside it); 0: no cone."""
    max_attempts: int = FROM_YAML
    """Give up after ``max_attempts * n`` tries without ``n`` touches that made contact."""
    lateral_offset: float = yaml_field(identity=lambda s: s.lateral_offset != 0)
    """How far each press lands off the gel's centre, as a fraction of the gel's half-width and half-height: each
    start pose moves sideways by a uniform draw within that box. 0 (the default): every press aims at the gel's
    centre, and the setting is no part of an item's identity."""

    def validate(self) -> None:
        at_least(self, 0, "n_touches", "n_val", "n_novel_view", "max_attempts")
        at_least(self, 1, "batch_size")
        if self.radius <= 0:
            raise SettingError("radius", f"must be > 0 metres, got {self.radius}")
        if not 0.0 <= self.lateral_offset <= 1.0:
            raise SettingError(
                "lateral_offset", f"must be in [0, 1] (a fraction of the gel), got {self.lateral_offset}"
            )


@dataclass
class TouchJob:
    """What ``tnf touch`` simulates, built from the run's config by the stage.

    ``settings`` is the ``touch`` section; ``simulator`` the simulator group's config node as a plain dict;
    ``config`` what decides an item's content (its hash); ``plan`` the force plan (None: every touch presses
    with ``settings.force``); ``names`` the objects still to simulate.
    """

    settings: TouchSettings
    sensor: Any
    simulator: dict[str, Any]
    source: Any
    names: list[str]
    config: dict[str, Any]
    plan: Any
    seed: int
    device: str
    progress: bool


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


def simulate_touches(job: TouchJob, store: Any, console: Any) -> None:
    """Simulate and write the touch item of each of ``job.names`` into ``store``."""
    import os
    from concurrent.futures import ThreadPoolExecutor

    tc = job.settings
    sim = SIMULATORS.build(job.simulator, sensor=job.sensor, device=job.device)
    counts = {"train": tc.n_touches, "val": tc.n_val, "novel_view": tc.n_novel_view}
    # What an item takes on disk, at least: its background, and each touch about the size of the background at the
    # touches' compression (a touch adds contact shading to it, so it compresses a little worse: ~1.3x measured).
    background_png = _png(sim.background)
    item_bytes = len(background_png) + sum(counts.values()) * len(_png(sim.background, level=1))
    # PNG encoding releases the GIL: a pool writes images while the simulator runs the next split.
    with progress(job.progress) as bar, ThreadPoolExecutor(max(1, min(16, os.cpu_count() or 1))) as pool:
        task = bar.add_task("touch", total=len(job.names) * sum(counts.values()))
        for name in job.names:
            touches, discarded = _simulate_item(
                job, store, sim, name, counts, background_png, item_bytes, pool, lambda: bar.advance(task)
            )
            n_disc = sum(discarded.values())
            sensor, src = job.sensor, job.source.name
            console.print(f"touch {sensor.name}/{src}/{name}: {len(touches)} touches, {n_disc} discarded")
            short = short_of_target(touches, tc.force)
            if short:
                lower = "touch.force" if job.plan is None else "touch.force_range"
                reached = [t.force or 0.0 for t in short]
                console.print(
                    f"[yellow]warning:[/] touch {sensor.name}/{src}/{name}: {len(short)} of {len(touches)} touches "
                    f"stopped at the deepest press (sensor.max_penetration, {sensor.cfg.max_penetration * 1e3:g} mm) "
                    f"short of their target force, at {min(reached):.2f}-{max(reached):.2f} N; each records the "
                    f"force it reached. Lower {lower} or raise sensor.max_penetration"
                )


def short_of_target(touches: list[TouchRecord], force: float, rel: float = 1e-3) -> list[TouchRecord]:
    """The touches whose recorded force is more than ``rel`` below their target (``force_target``, else
    ``force``, newtons): presses that stopped at the sensor's ``max_penetration``."""
    out = []
    for t in touches:
        target = force if t.force_target is None else t.force_target
        if t.force is not None and t.force < target * (1 - rel):
            out.append(t)
    return out


def _simulate_item(
    job: TouchJob,
    store: Any,
    sim: Any,
    name: str,
    counts: dict[str, int],
    background_png: bytes,
    item_bytes: int,
    pool: Any,
    advance: Any,
) -> tuple[list[TouchRecord], dict[str, int]]:
    """One object's item: every split's touches, written as they come; returns the touches and the discarded
    count of each split."""
    import numpy as np

    sensor, source, plan = job.sensor, job.source, job.plan
    mesh = source.load(name)
    seed = (job.seed * 1_000_003 + zlib.crc32(f"{source.name}/{name}".encode())) % 2**31
    rng = np.random.default_rng(seed)
    touches: list[TouchRecord] = []
    discarded = {}
    item = ("touch", sensor.name, source.name, name)
    info: dict[str, Any] = {}
    writes: list[Any] = []
    n_images = sum(counts.values())
    what = f"touch item {store.path(*item)} ({n_images} images of {sensor.width}x{sensor.height})"
    require_space(store.path(*item), item_bytes, what)  # before simulating what could not be stored
    with store.writing(*item, config=job.config, info=info) as tmp, _settled(writes):
        (tmp / "images").mkdir()
        (tmp / "background.png").write_bytes(background_png)
        for split_no, split in enumerate(SPLITS):
            if counts[split] == 0:
                discarded[split] = 0
                continue
            got = _collect(job, sim, mesh, counts[split], rng, split, seed + split_no)
            discarded[split] = got.discarded
            r = got.results
            for i in range(len(r.images)):
                index = len(touches)
                rel = f"images/{index:05d}.png"
                writes.append(pool.submit(_write_png, tmp / rel, r.images[i]))
                target = None if got.target_force is None or plan is None else float(got.target_force[i])
                touches.append(
                    TouchRecord(
                        index=index,
                        split=split,
                        image=rel,
                        start_c2w=as_matrix(got.start_c2w[i]),
                        contact_c2w=as_matrix(r.contact_c2w[i]),
                        contact_point=as_point(r.contact_point[i].astype(float)),
                        force=float(r.force[i]),
                        penetration=float(r.penetration[i]),
                        force_target=target,
                        force_band=None if target is None or plan is None else plan.band_of([target])[0],
                    )
                )
                advance()
        for w in writes:
            w.result()  # every image is on disk (or its error raised) before the item is finalised
        info.update(
            {
                "sensor": sensor.describe(),
                "object": name,
                "source": source.name,
                "touches": [t.to_json() for t in touches],
                "counts": {**{s: counts[s] for s in SPLITS}, "discarded": discarded},
                "width": sensor.width,
                "height": sensor.height,
                "intrinsics": list(sensor.intrinsics()),
            }
        )
        if plan is not None:
            info["force_range"] = plan.describe()
    return touches, discarded


def _collect(job: TouchJob, sim: Any, mesh: Any, count: int, rng: Any, split: str, seed: int) -> Any:
    """``count`` touches of one split (``tnf.sim.touch.collect``) with the touch section's settings."""

    tc = job.settings
    force = tc.force if job.plan is None else force_sampler(job.plan, split, seed)
    return collect(
        sim, mesh, count, rng,
        radius=tc.radius, force=force, batch_size=tc.batch_size,
        axis=list(tc.novel_view_axis), cone_deg=tc.novel_view_cone,
        inside=split == "novel_view", up=list(tc.up), random_roll=tc.random_roll,
        seed=seed, max_attempts=tc.max_attempts,
        lateral=(tc.lateral_offset * job.sensor.cfg.gel_width / 2, tc.lateral_offset * job.sensor.cfg.gel_height / 2),
    )  # fmt: skip
