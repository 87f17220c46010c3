"""``tnf touch``: simulate tactile touches of each selected object with the configured sensor.

Writes ``<data_root>/touch/<sensor>/<source>/<object>/``: ``images/00000.png``..., ``background.png`` and a
manifest whose info lists every touch (split, start and contact poses, contact point, force, penetration).
Finished items are skipped; ``-m sensor=digit,omnitact`` runs several sensors, ``-m shards=N 'shard=range(N)'``
splits the objects over N jobs (docs/cluster.md).
"""

from __future__ import annotations

from typing import Any

from tnf.artifacts import ArtifactStore, identity
from tnf.objects.captured import import_touches
from tnf.registry import SENSORS, from_dict, split_spec
from tnf.runtime import job_device, resolve_device, stage_console, warp_device
from tnf.sim.base import simulator_key
from tnf.sim.forces import force_plan
from tnf.sim.items import SPLITS, TouchJob, TouchSettings, simulate_touches
from tnf.stages import data_seed, run_objects, run_shard, shard_share

__all__ = ["SPLITS", "item_config", "run"]


def item_config(cfg: Any, sensor: Any, settings: TouchSettings | None = None) -> dict[str, Any]:
    """What decides a touch item's content (its hash decides whether a finished item is reused); ``settings``:
    the ``touch`` section, checked (from ``cfg`` when not given)."""
    tc = settings if settings is not None else from_dict(TouchSettings, cfg.touch, where="touch")
    return {
        "sensor": sensor.describe(),
        "simulator": split_spec(simulator_key(cfg.simulator), "simulator"),
        "touch": identity(tc),
        "seed": data_seed(cfg),
    }


def run(cfg: Any) -> None:
    from omegaconf import OmegaConf

    console = stage_console()
    tc = from_dict(TouchSettings, cfg.touch, where="touch")
    store = ArtifactStore(cfg.data_root)
    sensor = SENSORS.build(cfg.sensor)
    sensor.check_force(tc.force, "touch.force")
    plan = force_plan(tc.force_range, sensor)  # None: every touch presses with touch.force
    source, names = run_objects(cfg)
    names = shard_share(names, cfg)  # a job of a sweep over shards: its share
    if any(source.touches(n) is not None for n in names):  # the source's own tactile frames: imported, not simulated
        for n in names:
            console.print(import_touches(store, sensor, source, n, start_radius=tc.radius))
        return
    config = item_config(cfg, sensor, tc)
    todo = [n for n in names if not store.is_done("touch", sensor.name, source.name, n, config=config)]
    for n in names:
        if n not in todo:
            console.print(f"touch {sensor.name}/{source.name}/{n}: done, skipped")
    if not todo:
        return
    job = TouchJob(
        settings=tc,
        sensor=sensor,
        simulator=OmegaConf.to_container(cfg.simulator, resolve=True),  # type: ignore[arg-type]
        source=source,
        names=todo,
        config=config,
        plan=plan,
        seed=data_seed(cfg),
        device=warp_device(job_device(resolve_device(cfg.device), run_shard(cfg))),
        progress=bool(cfg.progress),
    )
    simulate_touches(job, store, console)
