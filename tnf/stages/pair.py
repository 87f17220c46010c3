"""``tnf pair``: pair every touch with RGB-D rendered at its pose, and build a dataset under ``pairs/``.

Inputs per selected object: the capture (``capture/<source>/<object>/transforms.json``, for the camera the
crop is measured in), the fitted scene (``scenes/<scene>/<source>/<object>/``; not needed with
``pair.scene_source=mesh``) and the touches (``touch/<sensor>/<source>/<object>/``). Every input is checked
before any rendering starts.

Two steps, both resumable: each object's touches are rendered and preprocessed into a cache item
(``pairs/.cache/<name>/<source>/<object>/``, skipped when done with the same settings), then the caches are
assembled into the dataset's memory-mapped arrays, chunk by chunk, with the split assignment. A job of a sweep over
object shards (``-m shards=N 'shard=range(N)'``, docs/cluster.md) renders its share's caches only; a run without
``shard`` then assembles the dataset, rendering whatever a killed job left undone.
"""

from __future__ import annotations

from typing import Any

from tnf.runtime import seed_everything
from tnf.stages import data_seed, run_objects, run_shard


def run(cfg: Any) -> None:
    from omegaconf import OmegaConf

    from tnf.data.pairing import PairJob, make_pairs
    from tnf.data.settings import PairSettings
    from tnf.data.store import dataset_name
    from tnf.registry import from_dict

    def plain(node: Any) -> Any:
        return OmegaConf.to_container(node, resolve=True) if node is not None else None

    settings = from_dict(PairSettings, cfg.pair, where="pair")
    seed_everything(data_seed(cfg))
    source, names = run_objects(cfg)
    job = PairJob(
        settings=settings,
        name=dataset_name(settings, str(cfg.sensor.name), str(cfg.scene.name)),
        data_root=str(cfg.data_root),
        source=source,
        names=names,
        sensor=plain(cfg.sensor),
        scene=plain(cfg.scene),
        simulator=plain(cfg.get("simulator")),
        objects=plain(cfg.objects),
        touch_force=float(cfg.touch.force),
        seed=data_seed(cfg),
        device=str(cfg.device),
        progress=bool(cfg.progress),
        shard=run_shard(cfg),
    )
    make_pairs(job)
