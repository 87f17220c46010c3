"""``tnf generate``: tactile images from novel poses of objects with a fitted scene.

For each selected object: sample ``generate.n_poses`` camera poses on a sphere around it (or read them from
``generate.poses_file``), render RGB-D from its fitted scene, preprocess as ``tnf pair`` does (the crop and
depth normalisation of the model's training dataset), run the trained generator with the sensor's background
image as condition, and write ``<data_root>/generated/<run_name>/<source>/<object>/`` in the format of
``tnf touch``: ``images/00000.png`` (128 x 128 generated tactile images), ``background.png`` and a manifest
whose ``touches`` hold each pose (``start_c2w``) and the point on its axis where the gel first meets the surface
(``contact_point``, from the scene's depth; null where no surface lies in the gel's footprint).
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from tnf.errors import TnfError


def read_poses(path: str | os.PathLike[str]) -> np.ndarray:
    """Camera-to-world poses [N, 4, 4] (metres, OpenGL) from ``.npy`` or ``.json`` (list, or ``{"poses": ...}``)."""
    p = Path(path).expanduser()
    if not p.is_file():
        raise TnfError(f"generate.poses_file not found: {p}")
    try:
        if p.suffix == ".npy":
            poses = np.load(p)
        else:
            data = json.loads(p.read_text())
            poses = np.asarray(data["poses"] if isinstance(data, dict) else data, dtype=np.float64)
    except (ValueError, KeyError, TypeError) as e:
        raise TnfError(f"generate.poses_file {p}: cannot read poses ({e})") from None
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4) or len(poses) == 0:
        raise TnfError(f"generate.poses_file {p}: expected [N, 4, 4] camera-to-world poses, got {poses.shape}")
    return poses


def sample_poses(n: int, radius: float, up: Any, random_roll: bool, seed: int) -> np.ndarray:
    """``n`` poses uniform on the sphere of ``radius`` metres, looking at the origin: [n, 4, 4] c2w."""
    from tnf.sim.touch import sphere_directions, start_poses

    rng = np.random.default_rng(seed)
    dirs = sphere_directions(rng, n, (0.0, 0.0, 1.0), 0.0, inside=False)
    return start_poses(rng, dirs, radius, up=list(up), random_roll=random_roll)


def run(cfg: Any) -> dict[str, Any]:
    import zlib
    from concurrent.futures import Future, ThreadPoolExecutor

    import torch
    from omegaconf import OmegaConf
    from PIL import Image
    from rich.console import Console

    from tnf.artifacts import ArtifactStore, read_json
    from tnf.data.preprocess import SIZE, gel_size_m, resize_uint8
    from tnf.data.render import Framing, render_rgbd_crops
    from tnf.generators import load_generator
    from tnf.objects import TOUCH_SPLITS, select
    from tnf.registry import SENSORS
    from tnf.runtime import progress, resolve_device
    from tnf.scenes import load_scene
    from tnf.sim.forces import requested_forces

    g = cfg.generate
    console = Console(highlight=False)
    if not g.model:
        raise TnfError("generate.model is not set: name a trained run under models/ (see `tnf train`)")
    if g.split not in TOUCH_SPLITS:
        raise TnfError(f"generate.split must be one of {', '.join(TOUCH_SPLITS)}, got {g.split!r}")
    store = ArtifactStore(cfg.data_root)
    model_dir = store.path("models", str(g.model))
    ckpt = model_dir / str(g.checkpoint)
    if not ckpt.is_file():
        raise TnfError(f"checkpoint not found: {ckpt}; train it with `tnf train` or check generate.model/checkpoint")
    device = resolve_device(str(cfg.device))
    system = load_generator(ckpt, device)
    size = int(system.hparams["generator"].get("image_size", SIZE))
    if size != SIZE:
        raise TnfError(f"model {g.model} generates {size} px images; tnf datasets use {SIZE} px")
    run_name = str(g.run_name or g.model)
    # The force of each image (generate.touch_force): a list of forces, "sim" or None (a model without force).
    wanted = requested_forces(
        g.get("touch_force"),
        system.hparams["generator"].get("force", "none") != "none",
        str(g.model),
        float(cfg.touch.force),
    )
    source, names = select(cfg)
    src = source.name
    sensor = SENSORS.build(cfg.sensor)
    gel = gel_size_m(sensor)
    background_full = sensor.background()
    background = resize_uint8(background_full, SIZE)
    mirror = sensor.mirror_channels() if g.mirror_average else None
    if g.mirror_average:
        console.print(
            f"generate: each image averaged with its mirror image ({sensor.name}'s mirror symmetry)"
            if mirror is not None
            else f"generate: {sensor.name} has no mirror symmetry; images are not mirror-averaged"
        )
    prep = _preprocessing(cfg, store, model_dir)
    # A generator that takes the prior (pair.prior) gets it made here the way `tnf pair` made it for training.
    needs_prior = "prior" in (system.hparams["generator"].get("inputs") or ())
    # A generator with a surface field (tnf.generators.field) gets each pixel's surface point and the object's
    # index in its training vocabulary (-1 for an object it never touched: the field then adds nothing).
    needs_points = "surface" in (system.hparams["generator"].get("inputs") or ())
    vocabulary = list((store.manifest("models", str(g.model)) or {}).get("object_names") or [])
    if needs_points and not vocabulary:
        raise TnfError(f"model {g.model} has a surface field but its manifest lists no object_names; retrain it")
    file_poses = read_poses(g.poses_file) if g.poses_file else None
    scene_name = str(cfg.scene.name)
    settings = OmegaConf.to_container(g, resolve=True)
    assert isinstance(settings, dict)

    # Check every input before any rendering.
    jobs = []
    prior: Any = None
    for obj in names:
        scene_dir = store.path("scenes", scene_name, src, obj)
        if not (scene_dir / "scene.pt").is_file():
            raise TnfError(
                f"object {obj!r} has no fitted {scene_name} scene ({scene_dir}); run `tnf fit-scene object={obj}`"
            )
        transforms = store.path("capture", src, obj) / "transforms.json"
        cam = read_json(transforms, "capture transforms")
        try:
            focal = (float(cam["fl_x"]), float(cam.get("fl_y", cam["fl_x"])))
        except (KeyError, TypeError, ValueError):
            raise TnfError(f"{transforms}: camera intrinsics missing; rerun `tnf capture object={obj}`") from None
        crop = g.crop_px or prep["crop_px"].get(obj)
        if crop is None and prep["footprint_distance"] is None:
            raise TnfError(
                f"no framing for {obj!r}: name the paired dataset (generate.dataset), or set pair.footprint_distance "
                "or generate.crop_px"
            )
        framing = Framing.from_settings(
            prep["framing"], crop_px=crop, footprint_distance=prep["footprint_distance"]
        ).with_sensor(sensor)
        if needs_prior and prior is None:
            from tnf.data.prior import DepthPrior
            from tnf.runtime import warp_device

            prior = DepthPrior(sensor, cfg.simulator, framing, device=warp_device(device))
        seed = (int(cfg.seed) * 1_000_003 + zlib.crc32(f"{src}/{obj}".encode())) % 2**31
        own: list[dict[str, Any]] | None = None  # generate.touch_force=sim: the object's simulated touches
        if wanted == "sim":
            from tnf.data.render import TouchItem

            own = TouchItem.load(
                store.require("touch", sensor.name, src, obj, hint=f"run `tnf touch object={obj}` first")
            ).touches
            unknown = [t["index"] for t in own if not isinstance(t.get("force"), (int, float))]
            if unknown:
                raise TnfError(
                    f"generate.touch_force=sim: touch {unknown[0]} of {obj!r} records no force (imported touches "
                    "record none); request a force in newtons instead"
                )
            poses = np.asarray([t["start_c2w"] for t in own], dtype=np.float64)
        else:
            poses = (
                file_poses
                if file_poses is not None
                else sample_poses(int(g.n_poses), float(g.radius), g.up, bool(g.random_roll), seed)
            )
        config = {
            "model": str(g.model),
            "checkpoint": str(g.checkpoint),
            "model_hash": (store.manifest("models", str(g.model)) or {}).get("config_hash"),
            "checkpoint_mtime": ckpt.stat().st_mtime_ns,
            "scene": scene_name,
            "scene_hash": (store.manifest("scenes", scene_name, src, obj) or {}).get("config_hash"),
            "sensor": sensor.describe(),
            "framing": dataclasses.asdict(framing),
            "poses": poses.round(9).tolist() if file_poses is not None else None,
            "settings": {
                k: v
                for k, v in settings.items()
                if k not in ("force", "batch_size", "render_chunk", "run_name")
                and not (k == "touch_force" and v is None)  # (hashes of items made before forces existed)
            },
            "seed": int(cfg.seed),
            # What makes the prior of a model that takes it: other settings make other images.
            "prior": (
                {"simulator": OmegaConf.to_container(cfg.simulator, resolve=True), "force": float(cfg.touch.force)}
                if needs_prior
                else None
            ),
        }
        if own is not None:  # generate.touch_force=sim: the touches' forces make the images too
            config["touch_forces"] = [t["force"] for t in own]
        if not g.force and store.is_done("generated", run_name, src, obj, config=config):
            console.print(f"generate: {run_name}/{src}/{obj} is up to date")
            continue
        jobs.append((obj, scene_dir, focal, framing, poses, config, seed, own))

    bg_t = torch.from_numpy(background).to(device).permute(2, 0, 1).float().div(127.5).sub(1)
    batch_size = int(g.batch_size)
    written = {}
    with progress(bool(cfg.progress)) as bar:
        per_pose = len(wanted) if isinstance(wanted, list) else 1
        task = bar.add_task("generate", total=sum(len(j[4]) * per_pose for j in jobs))
        for obj, scene_dir, focal, framing, poses, config, seed, own in jobs:
            # Each pose at each requested force: images pose-major (index = pose * forces + force's place).
            forces = (
                np.asarray([t["force"] for t in own], np.float32)
                if own is not None
                else np.asarray(wanted if isinstance(wanted, list) else [np.nan], np.float32)
            )
            step = max(1, batch_size // per_pose)
            # The generator's noise (dropout kept on when generating, as in pix2pix) comes from torch's RNG: seed
            # it per object, so that an object's images depend on the seed only and not on which objects this
            # process generated before (a resumed run generates only the missing ones).
            torch.manual_seed(seed)
            scene = load_scene(scene_dir, device)
            touches = []
            # PNG encoding on a few threads (PIL releases the GIL), overlapping the next batch's rendering.
            with (
                store.writing("generated", run_name, src, obj, config=config, info={}) as tmp,
                ThreadPoolExecutor(max_workers=min(8, os.cpu_count() or 1)) as pool,
            ):
                saves: list[Future] = []
                (tmp / "images").mkdir()
                Image.fromarray(background_full).save(tmp / "background.png")
                for s in range(0, len(poses), step):
                    c2w = torch.as_tensor(poses[s : s + step], dtype=torch.float32, device=device)
                    b = len(c2w)
                    with torch.no_grad():
                        rgb8, depth01, contact, points = render_rgbd_crops(
                            scene, c2w, focal, gel, framing, chunk=g.render_chunk, measure_contact=True,
                            with_points=needs_points,
                        )  # fmt: skip
                    batch = {
                        "rgb": torch.from_numpy(rgb8).to(device).permute(0, 3, 1, 2).float().div(127.5).sub(1),
                        "depth": torch.from_numpy(depth01.astype(np.float32)).to(device)[:, None].mul(2).sub(1),
                        "background": bg_t.expand(b, -1, -1, -1),
                    }
                    if points is not None:
                        batch["points"] = torch.from_numpy(points).to(device).permute(0, 3, 1, 2)
                        batch["object_id"] = torch.full((b,), vocabulary.index(obj) if obj in vocabulary else -1,
                                                        dtype=torch.long, device=device)  # fmt: skip
                    if prior is not None:
                        p8 = prior(depth01, float(cfg.touch.force))
                        batch["prior"] = torch.from_numpy(p8).to(device).permute(0, 3, 1, 2).float().div(127.5).sub(1)
                    image_force: list[float | None] = [None] * b
                    if wanted is not None:
                        batch, image_force = _at_forces(batch, forces, s, b, own is not None)
                    tactile = system.generate(batch, mirror)
                    images = ((tactile.float().clamp(-1, 1) + 1) * 127.5).round().to(torch.uint8)
                    images = images.permute(0, 2, 3, 1).cpu().numpy()
                    k = 1 if own is not None else per_pose  # images per pose in this batch
                    for i in range(b * k):
                        p_i = s + i // k
                        index = s * k + i
                        rel = f"images/{index:05d}.png"
                        saves.append(pool.submit(Image.fromarray(images[i]).save, tmp / rel))
                        pose = poses[p_i]
                        hit = bool(np.isfinite(contact[i // k]))
                        touches.append(
                            {
                                "index": index,
                                "split": str(own[p_i]["split"]) if own is not None else str(g.split),
                                "image": rel,
                                "start_c2w": pose.tolist(),
                                # Where the gel first meets the surface, on the sensor's axis (-z).
                                "contact_point": (pose[:3, 3] - contact[i // k] * pose[:3, 2]).tolist()
                                if hit
                                else None,
                                # The force the generator was asked for, newtons (null: a model without force).
                                "force": image_force[i],
                                "penetration": None,
                            }
                        )
                        if wanted is not None:
                            touches[-1]["pose_index"] = p_i
                    bar.advance(task, b * k)
                for f in saves:
                    f.result()  # re-raises a failed write
                from tnf.artifacts import write_json

                write_json(
                    tmp / "manifest.json",
                    {
                        "touches": touches,
                        "sensor": sensor.describe(),
                        "object": obj,
                        "source": src,
                        "counts": {str(g.split): len(touches), "discarded": 0},
                        "generator": {
                            "name": system.generator_name,
                            "model": str(g.model),
                            "checkpoint": str(ckpt),
                        },
                        "image_size": SIZE,
                        **(
                            {
                                "force": {
                                    "unit": "N",
                                    "requested": wanted,
                                    "per_pose": 1 if own is not None else per_pose,
                                }
                            }
                            if wanted is not None
                            else {}
                        ),
                    },
                )
            written[obj] = len(touches)
            del scene
    if written:
        console.print(
            f"generate: {sum(written.values())} tactile images for {len(written)} object(s) -> "
            f"{store.path('generated', run_name, src)}"
        )
    return {"run_dir": str(store.path("generated", run_name)), "written": written}


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


def _preprocessing(cfg: Any, store: Any, model_dir: Path) -> dict[str, Any]:
    """Crop and depth settings of the dataset the model was trained on (``generate.dataset`` overrides);
    falls back to the ``pair`` section when no dataset manifest is found."""
    from omegaconf import OmegaConf

    from tnf.artifacts import MANIFEST, read_json

    name = cfg.generate.dataset
    if name is None:
        m = store.manifest("models", model_dir.name) or {}
        datasets = m.get("datasets") or []
        name = datasets[0] if datasets else None
    pre: dict[str, Any] = {}
    if name is not None:
        folder = Path(str(name)).expanduser()
        if not (folder / MANIFEST).is_file():
            folder = store.path("pairs", str(name))
        if (folder / MANIFEST).is_file():
            pre = read_json(folder / MANIFEST, "dataset manifest").get("preprocess", {}) or {}
        elif cfg.generate.dataset is not None:
            raise TnfError(f"generate.dataset: no paired dataset {name!r} (looked in {folder})")
    crop = pre.get("crop_px", {})
    # Without a dataset manifest, the pair section's settings; otherwise the dataset's (older datasets lack
    # crop_distance and crop_margin: they used fixed crops, with pair's margin).
    pair = OmegaConf.to_container(cfg.pair, resolve=True)
    assert isinstance(pair, dict)
    framing = {k: v for k, v in (pre or pair).items() if k != "crop_px"}
    framing.setdefault("crop_margin", pair.get("crop_margin"))
    return {
        "crop_px": crop if isinstance(crop, dict) else {},
        "footprint_distance": pre.get("footprint_distance", pair.get("footprint_distance")),
        "framing": framing,
    }
