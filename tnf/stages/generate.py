"""``tnf generate``: tactile images from novel poses of objects with a fitted scene.

For each selected object: sample ``generate.n_poses`` camera poses on a sphere around it
(``generate.directions``: every direction, or the touch stage's held-out cone) or read them from
``generate.poses_file``, render RGB-D from its fitted scene, preprocess as ``tnf pair`` does (the crop and depth
normalisation of the model's training dataset), run the trained generator with the sensor's background image as
condition, and write ``<data_root>/generated/<run_name>/<source>/<object>/`` in the format of ``tnf touch``:
``images/00000.png`` (128 x 128 generated tactile images), ``background.png`` and a manifest whose ``touches``
hold each pose (``start_c2w``) and the point on its axis where the gel first meets the surface
(``contact_point``, from the scene's depth; null where no surface lies in the gel's footprint).

With ``generate.model`` unset, the model is the one ``tnf train`` trains with the same config (its run id,
``tnf.generators.names``).
"""

from __future__ import annotations

from typing import Any

from tnf.stages import run_objects


def run(cfg: Any) -> dict[str, Any]:
    import dataclasses

    from omegaconf import OmegaConf

    from tnf.data.settings import PairSettings
    from tnf.generators.generate import GenerateJob, GenerateSettings, generate
    from tnf.registry import from_dict
    from tnf.stages.train import model_run

    def plain(node: Any) -> Any:
        return OmegaConf.to_container(node, resolve=True) if node is not None else None

    source, names = run_objects(cfg)
    settings = from_dict(GenerateSettings, cfg.generate, where="generate")
    if not settings.model:  # the model `tnf train` trains with this config
        settings = dataclasses.replace(settings, model=model_run(cfg))
    job = GenerateJob(
        settings=settings,
        pair=from_dict(PairSettings, cfg.pair, where="pair"),
        data_root=str(cfg.data_root),
        source=source,
        names=names,
        sensor=plain(cfg.sensor),
        scene_name=str(cfg.scene.name),
        simulator=plain(cfg.get("simulator")),
        touch_force=float(cfg.touch.force),
        seed=int(cfg.seed),
        device=str(cfg.device),
        progress=bool(cfg.progress),
    )
    return generate(job)
