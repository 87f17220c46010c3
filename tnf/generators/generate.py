"""Tactile images from novel poses of objects with a fitted scene (``tnf generate``).

For each object: sample camera poses on a sphere around it (or take them from a file), render RGB-D from its
fitted scene, preprocess as ``tnf pair`` does (the crop and depth normalisation of the model's training
dataset), run the trained generator with the sensor's background image as condition, and write
``<data_root>/generated/<run_name>/<source>/<object>/`` in the format of ``tnf touch``: ``images/00000.png``
(128 x 128 generated tactile images), ``background.png`` and a manifest whose ``touches`` hold each pose
(``start_c2w``) and the point on its axis where the gel first meets the surface (``contact_point``, from the
scene's depth; null where no surface lies in the gel's footprint).
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from tnf.artifacts import MANIFEST, ArtifactStore, identity, read_json, write_json
from tnf.data.pairing import capture_camera
from tnf.data.preprocess import SIZE, gel_size_m, resize_uint8
from tnf.data.prior import DepthPrior
from tnf.data.render import Framing, TouchItem, render_rgbd_crops
from tnf.data.settings import PairSettings
from tnf.data.store import check_format
from tnf.errors import TnfError
from tnf.generators import load_generator
from tnf.generators.names import require_checkpoint
from tnf.generators.poses import pose_cone, pose_source, read_poses, sample_poses
from tnf.generators.settings import GenerateSettings
from tnf.registry import SENSORS
from tnf.runtime import progress, resolve_device, stage_console, warp_device
from tnf.scenes import load_scene
from tnf.sim.base import simulator_key
from tnf.sim.forces import requested_forces
from tnf.touches import TouchRecord, as_matrix, as_point


@dataclass
class GenerateJob:
    """What ``tnf generate`` makes, built from the run's config by the stage.

    ``settings`` is the ``generate`` section (its ``model`` set) and ``pair`` the ``pair`` section (the framing
    when the model's dataset is not found); ``sensor`` and ``simulator`` are those groups' config nodes as plain
    dicts.
    """

    settings: GenerateSettings
    pair: PairSettings
    data_root: str
    source: Any
    names: list[str]
    sensor: dict[str, Any]
    scene_name: str
    simulator: dict[str, Any] | None
    touch_force: float
    seed: int
    device: str
    progress: bool


@dataclass
class _Model:
    """The loaded generator and what every object's images share."""

    system: Any
    ckpt: Path
    run_name: str
    wanted: list[float] | str | None
    sensor: Any
    gel: tuple[float, float]
    background_full: np.ndarray
    background: np.ndarray
    mirror: Any
    needs_prior: bool
    needs_points: bool
    vocabulary: list[str]
    device: str
    prior: Any = None  # the DepthPrior of a model that takes it, built with the first object's framing


def generate(job: GenerateJob) -> dict[str, Any]:
    """Generate the images of every object not already done with the same settings.

    Returns ``{"run_dir": <generated/run_name>, "written": {object: images written}}``."""
    console = stage_console()
    store = ArtifactStore(job.data_root)
    model = _load_model(job, store, console)
    jobs = _plan(job, store, model, console)
    written = {}
    with progress(job.progress) as bar:
        per_pose = len(model.wanted) if isinstance(model.wanted, list) else 1
        task = bar.add_task("generate", total=sum(len(j[4]) * per_pose for j in jobs))
        for item in jobs:
            written[item[0]] = _generate_object(job, store, model, item, lambda k: bar.advance(task, k))
    if written:
        console.print(
            f"generate: {sum(written.values())} tactile images for {len(written)} object(s) -> "
            f"{store.path('generated', model.run_name, job.source.name)}"
        )
    return {"run_dir": str(store.path("generated", model.run_name)), "written": written}


def _load_model(job: GenerateJob, store: Any, console: Any) -> _Model:
    """Check the settings, load the checkpoint and build the sensor."""

    g = job.settings
    if not g.model:
        raise TnfError("generate.model is not set: name a trained run under models/ (see `tnf train`)")
    ckpt = require_checkpoint(store.path("models", g.model) / g.checkpoint, "generate.model")
    device = resolve_device(job.device)
    system = load_generator(ckpt, device)
    hp = system.hparams["generator"]
    size = int(hp.get("image_size", SIZE))
    if size != SIZE:
        raise TnfError(f"model {g.model} generates {size} px images; tnf datasets use {SIZE} px")
    # The force of each image (generate.touch_force): a list of forces, "sim" or None (a model without force).
    wanted = requested_forces(g.touch_force, hp.get("force", "none") != "none", g.model, job.touch_force)
    sensor = SENSORS.build(job.sensor)
    for f in wanted if isinstance(wanted, list) else ():
        sensor.check_force(f, "touch.force" if g.touch_force is None else "generate.touch_force")
    if isinstance(wanted, list) and g.touch_force is not None:
        _warn_untrained_forces(wanted, _trained_forces(store, g.model), g.model, console)
    background_full = sensor.background()
    mirror = sensor.mirror_channels() if g.mirror_average else None
    if g.mirror_average:
        console.print(
            f"generate: each image averaged with its mirror image ({sensor.name}'s mirror symmetry)"
            if mirror is not None
            else f"generate: {sensor.name} has no mirror symmetry; images are not mirror-averaged"
        )
    # A generator with a surface field (tnf.generators.field) gets each pixel's surface point and the object's
    # index in its training vocabulary (-1 for an object it never touched: the field then adds nothing).
    needs_points = "surface" in (hp.get("inputs") or ())
    vocabulary = list((store.manifest("models", g.model) or {}).get("object_names") or [])
    if needs_points and not vocabulary:
        raise TnfError(f"model {g.model} has a surface field but its manifest lists no object_names; retrain it")
    return _Model(
        system=system,
        ckpt=ckpt,
        run_name=g.run_name or g.model,
        wanted=wanted,
        sensor=sensor,
        gel=gel_size_m(sensor),
        background_full=background_full,
        background=resize_uint8(background_full, SIZE),
        mirror=mirror,
        # A generator that takes the prior (pair.prior) gets it made here the way `tnf pair` made it for training.
        needs_prior="prior" in (hp.get("inputs") or ()),
        needs_points=needs_points,
        vocabulary=vocabulary,
        device=device,
    )


def _trained_forces(store: Any, model: str) -> tuple[float, float] | None:
    """The force range (newtons) of the pairs ``model`` trained on, from its datasets' manifests; None when they
    record none (pairs of one force, or a model trained elsewhere)."""
    ranges = []
    for name in (store.manifest("models", model) or {}).get("datasets") or ():
        rng = ((store.manifest("pairs", name) or {}).get("force") or {}).get("range")
        if not rng:
            return None
        ranges.append((float(rng["min"]), float(rng["max"])))
    if not ranges:
        return None
    return min(lo for lo, _ in ranges), max(hi for _, hi in ranges)


def _warn_untrained_forces(wanted: list[float], trained: tuple[float, float] | None, model: str, console: Any) -> None:
    """A warning when ``generate.touch_force`` asks for forces outside the range ``model`` trained on: its images
    there are extrapolation (the sensor may press them; the generator never saw them)."""
    if trained is None:
        return
    lo, hi = trained
    outside = [f for f in wanted if not lo <= f <= hi]
    if outside:
        shown = ", ".join(f"{f:g}" for f in outside[:5]) + (", ..." if len(outside) > 5 else "")
        console.print(
            f"[yellow]warning:[/] generate.touch_force: {shown} N lie outside the forces model {model!r} trained on "
            f"({lo:g}-{hi:g} N); its touches there are extrapolated"
        )


def _plan(job: GenerateJob, store: Any, model: _Model, console: Any) -> list[tuple[Any, ...]]:
    """Check every object's inputs before any rendering; the objects not yet done, each with its scene folder,
    focal lengths, framing, poses, config, seed and (``touch_force=sim``) its simulated touches."""
    import zlib

    g, src = job.settings, job.source.name
    prep = _preprocessing(job, store)
    file_poses = read_poses(g.poses_file) if g.poses_file else None
    cone = pose_cone(g)
    jobs = []
    for obj in job.names:
        scene_dir = store.path("scenes", job.scene_name, src, obj)
        if not (scene_dir / "scene.pt").is_file():
            raise TnfError(
                f"object {obj!r} has no fitted {job.scene_name} scene ({scene_dir}); run `tnf fit-scene object={obj}`"
            )
        transforms = store.path("capture", src, obj) / "transforms.json"
        focal, _, _ = capture_camera(read_json(transforms, "capture transforms"), transforms)
        crop = g.crop_px or prep["crop_px"].get(obj)
        if crop is None and prep["footprint_distance"] is None:
            raise TnfError(
                f"no framing for {obj!r}: name the paired dataset (generate.dataset), or set pair.footprint_distance "
                "or generate.crop_px"
            )
        framing = Framing.from_settings(
            prep["framing"], crop_px=crop, footprint_distance=prep["footprint_distance"]
        ).with_sensor(model.sensor)
        if model.needs_prior and model.prior is None:
            model.prior = DepthPrior(model.sensor, job.simulator, framing, device=warp_device(model.device))
        seed = (job.seed * 1_000_003 + zlib.crc32(f"{src}/{obj}".encode())) % 2**31
        own = _own_touches(store, model.sensor.name, src, obj) if model.wanted == "sim" else None
        if own is not None:
            poses = np.asarray([t.start_c2w for t in own], dtype=np.float64)
        elif file_poses is not None:
            poses = file_poses
        else:
            poses = sample_poses(g.n_poses, g.radius, g.up, g.random_roll, seed, cone=cone)
        config = _item_config(job, store, model, obj, framing, poses if file_poses is not None else None, own)
        if not g.force and store.is_done("generated", model.run_name, src, obj, config=config):
            console.print(f"generate: {model.run_name}/{src}/{obj} is up to date")
            continue
        jobs.append((obj, scene_dir, focal, framing, poses, config, seed, own))
    return jobs


def _own_touches(store: Any, sensor: str, src: str, obj: str) -> list[TouchRecord]:
    """``generate.touch_force=sim``: the object's simulated touches, each with its recorded force."""

    own = TouchItem.load(store.require("touch", sensor, src, obj, hint=f"run `tnf touch object={obj}` first")).touches
    unknown = [t.index for t in own if t.force is None]
    if unknown:
        raise TnfError(
            f"generate.touch_force=sim: touch {unknown[0]} of {obj!r} records no force (imported touches "
            "record none); request a force in newtons instead"
        )
    return own


def _item_config(
    job: GenerateJob,
    store: Any,
    model: _Model,
    obj: str,
    framing: Any,
    file_poses: np.ndarray | None,
    own: list[TouchRecord] | None,
) -> dict[str, Any]:
    """What decides an object's images (its hash decides whether a finished item is reused)."""
    g, src = job.settings, job.source.name
    config = {
        "model": g.model,
        "checkpoint": g.checkpoint,
        "model_hash": (store.manifest("models", str(g.model)) or {}).get("config_hash"),
        "checkpoint_mtime": model.ckpt.stat().st_mtime_ns,
        "scene": job.scene_name,
        "scene_hash": (store.manifest("scenes", job.scene_name, src, obj) or {}).get("config_hash"),
        "sensor": model.sensor.describe(),
        "framing": dataclasses.asdict(framing),
        "poses": file_poses.round(9).tolist() if file_poses is not None else None,
        "settings": identity(g),
        "seed": job.seed,
        "prior": _prior_key(job) if model.needs_prior else None,
    }
    if own is not None:  # generate.touch_force=sim: the touches' forces make the images too
        config["touch_forces"] = [t.force for t in own]
    return config


def _prior_key(job: GenerateJob) -> dict[str, Any]:
    """What makes the prior of a model that takes it: other settings make other images."""
    simulator = simulator_key(job.simulator) if job.simulator is not None else None
    return {"simulator": simulator, "force": job.touch_force}


def _generate_object(job: GenerateJob, store: Any, model: _Model, item: tuple[Any, ...], advance: Any) -> int:
    """Render, generate and write one object's images; returns how many were written."""
    from concurrent.futures import Future, ThreadPoolExecutor

    import torch
    from PIL import Image

    obj, scene_dir, focal, framing, poses, config, seed, own = item
    wanted = model.wanted
    per_pose = len(wanted) if isinstance(wanted, list) else 1
    # Each pose at each requested force: images pose-major (index = pose * forces + force's place).
    forces = (
        np.asarray([t.force for t in own], np.float32)
        if own is not None
        else np.asarray(wanted if isinstance(wanted, list) else [np.nan], np.float32)
    )
    step = max(1, job.settings.batch_size // per_pose)
    # The generator's noise (dropout kept on when generating, as in pix2pix) comes from torch's RNG: seed
    # it per object, so that an object's images depend on the seed only and not on which objects this
    # process generated before (a resumed run generates only the missing ones).
    torch.manual_seed(seed)
    scene = load_scene(scene_dir, model.device)
    touches: list[TouchRecord] = []
    # PNG encoding on a few threads (PIL releases the GIL), overlapping the next batch's rendering.
    with (
        store.writing("generated", model.run_name, job.source.name, obj, config=config, info={}) as tmp,
        ThreadPoolExecutor(max_workers=min(8, os.cpu_count() or 1)) as pool,
    ):
        saves: list[Future] = []
        (tmp / "images").mkdir()
        Image.fromarray(model.background_full).save(tmp / "background.png")
        for s in range(0, len(poses), step):
            images, contact, image_force = _generate_batch(
                job, model, scene, obj, focal, framing, poses, forces, s, step
            )
            b = len(contact)
            k = 1 if own is not None else per_pose  # images per pose in this batch
            for i in range(b * k):
                rel = f"images/{s * k + i:05d}.png"
                saves.append(pool.submit(Image.fromarray(images[i]).save, tmp / rel))
                split = own[s + i // k].split if own is not None else job.settings.split
                touches.append(
                    _touch_record(s * k + i, s + i // k, split, rel, poses, contact[i // k], image_force[i], wanted)
                )
            advance(b * k)
        for f in saves:
            f.result()  # re-raises a failed write
        write_json(tmp / "manifest.json", _manifest(job, model, obj, touches, 1 if own is not None else per_pose))
    del scene
    return len(touches)


def _generate_batch(
    job: GenerateJob,
    model: _Model,
    scene: Any,
    obj: str,
    focal: tuple[float, float],
    framing: Any,
    poses: np.ndarray,
    forces: np.ndarray,
    s: int,
    step: int,
) -> tuple[np.ndarray, np.ndarray, list[float | None]]:
    """The images [B * k, 128, 128, 3] uint8 of poses ``s .. s + step`` (k per pose), each pose's contact
    distance along its axis (metres; inf where the gel's footprint holds no surface) and each image's force."""
    import torch

    device = model.device
    c2w = torch.as_tensor(poses[s : s + step], dtype=torch.float32, device=device)
    b = len(c2w)
    with torch.no_grad():
        rgb8, depth01, contact, points = render_rgbd_crops(
            scene, c2w, focal, model.gel, framing, chunk=job.settings.render_chunk, measure_contact=True,
            with_points=model.needs_points,
        )  # fmt: skip
    batch = condition_batch(rgb8, depth01, model.background, device)
    if points is not None:
        batch["points"] = torch.from_numpy(points).to(device).permute(0, 3, 1, 2)
        batch["object_id"] = torch.full((b,), model.vocabulary.index(obj) if obj in model.vocabulary else -1,
                                        dtype=torch.long, device=device)  # fmt: skip
    if model.prior is not None:
        p8 = model.prior(depth01, job.touch_force)
        batch["prior"] = torch.from_numpy(p8).to(device).permute(0, 3, 1, 2).float().div(127.5).sub(1)
    image_force: list[float | None] = [None] * b
    if model.wanted is not None:
        batch, image_force = _at_forces(batch, forces, s, b, model.wanted == "sim")
    return tactile_images(model.system, batch, model.mirror), contact, image_force


def condition_batch(rgb8: np.ndarray, depth01: np.ndarray, background: np.ndarray, device: Any) -> dict[str, Any]:
    """A generator's conditions from preprocessed RGB-D crops (``render_rgbd_crops``): ``rgb8`` uint8
    [B, S, S, 3], ``depth01`` [B, S, S] in [0, 1] and the sensor's ``background`` uint8 [S, S, 3], as float32
    tensors in [-1, 1] on ``device``: ``rgb`` [B, 3, S, S], ``depth`` [B, 1, S, S], ``background`` [B, 3, S, S]
    (a stride-0 view of one image)."""
    import torch

    b = len(rgb8)
    bg_t = torch.from_numpy(np.ascontiguousarray(background)).to(device).permute(2, 0, 1).float().div(127.5).sub(1)
    return {
        "rgb": torch.from_numpy(np.ascontiguousarray(rgb8)).to(device).permute(0, 3, 1, 2).float().div(127.5).sub(1),
        "depth": torch.from_numpy(np.asarray(depth01, np.float32)).to(device)[:, None].mul(2).sub(1),
        "background": bg_t.expand(b, -1, -1, -1),
    }


def tactile_images(system: Any, batch: dict[str, Any], mirror: Any = None) -> np.ndarray:
    """``system.generate(batch, mirror)`` as uint8 [B, S, S, 3] images."""
    import torch

    tactile = system.generate(batch, mirror)
    images = ((tactile.float().clamp(-1, 1) + 1) * 127.5).round().to(torch.uint8)
    return images.permute(0, 2, 3, 1).cpu().numpy()


def _touch_record(
    index: int,
    p_i: int,
    split: str,
    rel: str,
    poses: np.ndarray,
    contact: float,
    force: float | None,
    wanted: Any,
) -> TouchRecord:
    """One generated image's record in the manifest's ``touches`` (the format of ``tnf touch``)."""
    pose = poses[p_i]
    hit = bool(np.isfinite(contact))
    return TouchRecord(
        index=index,
        split=split,
        image=rel,
        start_c2w=as_matrix(pose),
        # Where the gel first meets the surface, on the sensor's axis (-z).
        contact_point=as_point(pose[:3, 3] - contact * pose[:3, 2]) if hit else None,
        # The force the generator was asked for, newtons (None: a model without force).
        force=force,
        penetration=None,
        pose_index=p_i if wanted is not None else None,
    )


def _manifest(job: GenerateJob, model: _Model, obj: str, touches: list[TouchRecord], per_pose: int) -> dict[str, Any]:

    g = job.settings
    return {
        "touches": [t.to_json() for t in touches],
        "sensor": model.sensor.describe(),
        "object": obj,
        "source": job.source.name,
        "counts": {g.split: len(touches), "discarded": 0},
        "generator": {"name": model.system.generator_name, "model": g.model, "checkpoint": str(model.ckpt)},
        "image_size": SIZE,
        "poses": pose_source(g, sim=model.wanted == "sim"),
        **(
            {"force": {"unit": "N", "requested": model.wanted, "per_pose": per_pose}}
            if model.wanted is not None
            else {}
        ),
    }


def _at_forces(
    batch: dict[str, Any], forces: np.ndarray, start: int, b: int, own: bool
) -> tuple[dict[str, Any], list[float | None]]:
    """The batch of ``b`` poses (from pose ``start``) with a ``force`` key: with ``own``, pose i's force is
    ``forces[start + i]``; otherwise every pose is repeated at each of ``forces`` (pose-major). Returns it and the
    force of each image, newtons."""
    import torch

    if own:
        f = torch.from_numpy(forces[start : start + b].copy())
        out = dict(batch)
    else:
        k = len(forces)
        out = {key: v.repeat_interleave(k, 0) if isinstance(v, torch.Tensor) else v for key, v in batch.items()}
        f = torch.from_numpy(np.tile(forces, b))
    out["force"] = f.to(batch["rgb"].device)
    return out, [round(float(x), 6) for x in f.tolist()]


def _preprocessing(job: GenerateJob, store: Any) -> dict[str, Any]:
    """Crop and depth settings of the dataset the model was trained on (``generate.dataset`` overrides);
    falls back to the ``pair`` section when that dataset has no manifest. A model without a manifest (its
    training cut short, or not made by ``tnf train``) names no dataset: refused unless ``generate.dataset`` is set."""

    name = job.settings.dataset
    if name is None:
        model = store.path("models", str(job.settings.model)).name
        m = store.manifest("models", model)
        if m is None:
            # The pair section's framing may not be the one it trained on.
            raise TnfError(
                f"model {model} has not finished training (no {MANIFEST} in {store.path('models', model)}): "
                "finish it with the same `tnf train` command (it resumes), or name the paired dataset it trains on "
                "(generate.dataset=...) to generate from its checkpoint as it is"
            )
        datasets = m.get("datasets") or []
        name = datasets[0] if datasets else None
    pre: dict[str, Any] = {}
    if name is not None:
        folder = Path(str(name)).expanduser()
        if not (folder / MANIFEST).is_file():
            folder = store.path("pairs", str(name))
        if (folder / MANIFEST).is_file():
            manifest = read_json(folder / MANIFEST, "dataset manifest")
            check_format(manifest, folder)
            pre = manifest.get("preprocess", {}) or {}
        elif job.settings.dataset is not None:
            raise TnfError(f"generate.dataset: no paired dataset {name!r} (looked in {folder})")
    crop = pre.get("crop_px", {})
    # The dataset's framing; without a dataset manifest, the pair section's.
    framing = {k: v for k, v in (pre or dataclasses.asdict(job.pair)).items() if k != "crop_px"}
    return {
        "crop_px": crop if isinstance(crop, dict) else {},
        "footprint_distance": framing["footprint_distance"],
        "framing": framing,
    }
