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

import dataclasses
import json
import shutil
from pathlib import Path
from typing import Any, cast

from tnf.errors import TnfError

ASSEMBLE_CHUNK = 256  # pairs copied per step while assembling (bounds memory)


def run(cfg: Any) -> None:
    import numpy as np
    from omegaconf import OmegaConf
    from rich.console import Console

    from tnf.artifacts import ArtifactStore, read_json
    from tnf.data.preprocess import SIZE, crop_origin, gel_size_m
    from tnf.data.render import Framing, TouchItem, render_pairs_for_touches
    from tnf.data.splits import SPLITS, assign_splits, choose_novel_objects
    from tnf.data.store import PairWriter, dataset_name, write_manifest
    from tnf.objects import select, shard, shard_of
    from tnf.registry import SENSORS, config_to_dict, split_spec
    from tnf.runtime import job_device, progress, resolve_device, seed_everything, warp_device

    p = cast(dict[str, Any], OmegaConf.to_container(cfg.pair, resolve=True))
    assert isinstance(p, dict)
    if p["scene_source"] not in ("fitted", "mesh"):
        raise TnfError(f"pair.scene_source must be 'fitted' or 'mesh', got {p['scene_source']!r}")
    seed_everything(int(cfg.seed))
    store = ArtifactStore(cfg.data_root)
    source, names = select(cfg)
    src = source.name
    sensor_name, sensor_params = split_spec(cfg.sensor, "sensor")
    sensor_cfg = SENSORS.config(sensor_name, sensor_params)
    sensor = SENSORS.get(sensor_name)(sensor_cfg)
    sensor_dict = _plain_json(config_to_dict(sensor_cfg))
    scene_name = str(cfg.scene.name)
    name = dataset_name(cfg)
    part = shard_of(cfg)
    device = job_device(resolve_device(str(cfg.device)), part)
    console = Console(highlight=False)

    # -- check every input first, so a missing one is reported before hours of rendering ----------------
    inputs: dict[str, dict[str, Any]] = {}
    for obj in names:
        touch_dir = store.require(
            "touch", sensor_name, src, obj, hint=f"run `tnf touch object={obj} sensor={sensor_name}` first"
        )
        item = TouchItem.load(touch_dir)
        _check_sensor(item, sensor_name, sensor_dict, obj)
        transforms = store.path("capture", src, obj) / "transforms.json"
        if not transforms.is_file():
            raise TnfError(f"object {obj!r}: capture not found ({transforms}); run `tnf capture object={obj}`")
        cam = read_json(transforms, "capture transforms")
        focal, w, h = _focal(cam, transforms)
        scene_dir = store.path("scenes", scene_name, src, obj)
        scene_hash = None
        if p["scene_source"] == "fitted":
            if not (scene_dir / "scene.pt").is_file():
                raise TnfError(
                    f"object {obj!r} has touches but no fitted {scene_name} scene ({scene_dir}); "
                    f"run `tnf fit-scene object={obj} scene={scene_name}` first, or use pair.scene_source=mesh"
                )
            scene_hash = (store.manifest("scenes", scene_name, src, obj) or {}).get("config_hash")
        inputs[obj] = {"item": item, "focal": focal, "size": (w, h), "scene_dir": scene_dir, "scene_hash": scene_hash}

    # -- framing: the crop and depth settings; the reference distance is the touches' median ------------
    distance = p.get("footprint_distance")
    if distance is None:
        all_d = np.concatenate([i["item"].contact_distances() for i in inputs.values()])
        all_d = all_d[np.isfinite(all_d) & (all_d > 0)]
        if len(all_d):
            distance = float(np.median(all_d))
        elif p["crop_px"] is None:
            raise TnfError(
                "no touch records a contact in front of its start pose; cannot size the crop (set pair.crop_px)"
            )
    framing = Framing.from_settings(p, footprint_distance=distance).with_sensor(sensor)
    gel = gel_size_m(sensor)
    for obj, i in inputs.items():
        i["crop_px"] = None if framing.per_view else framing.fixed_crop(i["focal"], gel)
        if i["crop_px"] is not None:
            try:
                width, height = i["size"]
                crop_origin(width, height, i["crop_px"])
            except TnfError as e:
                raise TnfError(f"object {obj!r}: {e} (the capture camera's image)") from None

    # -- step 1: per-object render caches -----------------------------------------------------------------
    optional = tuple(k for k in ("prior", "points") if p[k])
    assembled = optional + (("force",) if p.get("force") else ())
    cache_keys: dict[str, dict[str, Any]] = {}
    for obj, i in inputs.items():
        key = {
            "scene_source": p["scene_source"],
            "scene": scene_name if p["scene_source"] == "fitted" else "mesh",
            "scene_hash": i["scene_hash"],
            "touch_hash": i["item"].manifest.get("config_hash"),
            "touches": len(i["item"].touches),
            **dataclasses.asdict(framing),
            "crop_px": i["crop_px"],
            "focal": list(i["focal"]),
            "size": SIZE,
        }
        if p["prior"]:
            key["prior"] = _plain_json(cfg.simulator)
        if p["points"]:
            key["points"] = True
        cache_keys[obj] = key
    # A finished dataset made from the same inputs needs nothing, not even its (deleted) render caches.
    novel = choose_novel_objects(names, p["novel_objects"], int(p["num_novel_objects"]), int(cfg.seed))
    dataset_key = {"objects": names, "novel_objects": novel, "caches": cache_keys, "source": src}
    touch_force = None
    if p.get("force"):  # pair.force: each pair's touch force (force.npy), read from the touch manifests
        from tnf.data.forces import touch_forces

        touch_force = touch_forces({o: inputs[o]["item"] for o in names})
        dataset_key["force"] = touch_force.record
    if store.is_done("pairs", name, config=dataset_key):
        console.print(f"pair: dataset {store.path('pairs', name)} is up to date")
        return
    # Every object's inputs decide the framing above; a job of a sweep over shards renders its share only.
    mine = shard(names, cfg)
    todo = [o for o in mine if not store.is_done("pairs", ".cache", name, src, o, config=cache_keys[o])]
    n_render = sum(len(inputs[o]["item"].touches) for o in todo)
    if todo:
        console.print(f"pair: rendering {n_render} touches of {len(todo)} object(s) on {device} ({p['scene_source']})")
    prior = None
    if p["prior"]:
        from tnf.data.prior import DepthPrior

        prior = DepthPrior(sensor, cfg.simulator, framing, device=warp_device(device))
        console.print(f"pair: with the prior, {cfg.simulator.name}'s image of each depth crop (pair.prior)")
    with progress(bool(cfg.progress)) as bar:
        task = bar.add_task(f"render {name}", total=n_render)
        for obj in todo:
            i = inputs[obj]
            scene = _load_scene(p["scene_source"], i["scene_dir"], source, obj, device)
            arrays = render_pairs_for_touches(
                scene,
                i["item"],
                sensor,
                framing,
                focal=i["focal"],
                device=device,
                render_batch=int(p["render_batch"]),
                render_chunk=p.get("render_chunk"),
                on_batch=lambda k: bar.advance(task, k),
                with_points=bool(p["points"]),
            )
            del scene
            if prior is not None:
                # Each touch's recorded force (imported touches may record none: touch.force then).
                forces = [t.get("force") or float(cfg.touch.force) for t in i["item"].touches]
                arrays["prior"] = prior(arrays["depth"], np.asarray(forces, np.float32))
            labels = [t["split"] for t in i["item"].touches]
            assign_splits(labels, novel_object=False)  # validates the labels before caching
            with store.writing(
                "pairs", ".cache", name, src, obj, config=cache_keys[obj], info={"splits": labels}
            ) as tmp:
                for k in ("rgb", "depth", "tactile", "background", "touch_index", *optional):
                    np.save(tmp / f"{k}.npy", arrays[k])
            del arrays

    if part is not None:
        console.print(
            f"pair: shard {part[0]} of {part[1]}: {len(mine) - len(todo)} object(s) already rendered, {len(todo)} "
            "rendered now; `tnf pair` without shard assembles the dataset"
        )
        return

    # -- step 2: assemble ---------------------------------------------------------------------------------
    caches = {o: store.path("pairs", ".cache", name, src, o) for o in names}
    counts = {o: len(inputs[o]["item"].touches) for o in names}
    n = sum(counts.values())
    if n == 0:
        raise TnfError(f"the touch data of {', '.join(names)} has no touches; rerun `tnf touch`")
    backgrounds: list[np.ndarray] = []
    bg_of: dict[str, int] = {}
    for o in names:
        bg = np.load(caches[o] / "background.npy")
        match = [j for j, b in enumerate(backgrounds) if np.array_equal(b, bg)]
        if not match:
            backgrounds.append(bg)
        bg_of[o] = match[0] if match else len(backgrounds) - 1
    split_counts = dict.fromkeys(SPLITS, 0)
    with store.writing("pairs", name, config=dataset_key) as tmp:
        start = 0
        with PairWriter(tmp, n, np.stack(backgrounds), optional=assembled) as writer:
            for oid, o in enumerate(names):
                labels = (store.manifest("pairs", ".cache", name, src, o) or {})["splits"]
                codes = assign_splits(labels, novel_object=o in novel)
                for c in codes:
                    split_counts[SPLITS[c]] += 1
                arr = {
                    k: np.load(caches[o] / f"{k}.npy", mmap_mode="r")
                    for k in ("rgb", "depth", "tactile", "touch_index", *optional)
                }
                for s in range(0, counts[o], ASSEMBLE_CHUNK):
                    end = min(s + ASSEMBLE_CHUNK, counts[o])
                    n_chunk = end - s
                    writer.write(
                        start + s,
                        rgb=arr["rgb"][s:end],
                        depth=arr["depth"][s:end],
                        tactile=arr["tactile"][s:end],
                        touch_index=arr["touch_index"][s:end],
                        background_index=np.full(n_chunk, bg_of[o], np.int32),
                        object_id=np.full(n_chunk, oid, np.int32),
                        split=codes[s:end],
                        sensor_id=np.zeros(n_chunk, np.int16),
                        **{k: arr[k][s:end] for k in optional},
                        **({"force": touch_force.of(o, arr["touch_index"][s:end])} if touch_force is not None else {}),
                    )
                start += counts[o]
        first = inputs[names[0]]["item"].manifest
        write_manifest(
            tmp,
            {
                "name": name,
                "objects": names,
                "sensors": [sensor_name],
                "novel_objects": novel,
                "count": n,
                "counts": {s: c for s, c in split_counts.items()},
                "counts_per_object": counts,
                "object_source": _plain_json(cfg.objects),
                "sensor": {"name": sensor_name, "config": sensor_dict},
                "simulator": _plain_json(first.get("config", {}).get("simulator", cfg.get("simulator"))),
                "touch_config_hashes": {o: inputs[o]["item"].manifest.get("config_hash") for o in names},
                "scene_source": p["scene_source"],
                # pair.prior: the simulator that made prior.npy from the depth crops (tnf.data.prior).
                "prior": {"simulator": _plain_json(cfg.simulator)} if p["prior"] else None,
                # pair.points: points.npy holds each RGB-D pixel's surface point (tnf.data.render.crop_points).
                "points": {"frame": "object", "unit": "m"} if p["points"] else None,
                # pair.force: force.npy holds each pair's touch force; the touches' force range and bands.
                **({"force": touch_force.record} if touch_force is not None else {}),
                "scene": _plain_json(cfg.scene) if p["scene_source"] == "fitted" else {"name": "mesh"},
                "scene_checkpoints": {
                    o: (str(inputs[o]["scene_dir"] / "scene.pt") if p["scene_source"] == "fitted" else None)
                    for o in names
                },
                "scene_config_hashes": {o: inputs[o]["scene_hash"] for o in names},
                "preprocess": {
                    **dataclasses.asdict(framing),
                    "crop_px": {o: inputs[o]["crop_px"] for o in names if inputs[o]["crop_px"] is not None},
                    "size": SIZE,
                },
            },
        )
        _write_previews(tmp, names, int(p["previews"]), int(cfg.seed))
    if not p["keep_cache"]:
        shutil.rmtree(store.path("pairs", ".cache", name), ignore_errors=True)
    _summary(console, store.path("pairs", name), n, split_counts, names, novel)


def _focal(cam: dict[str, Any], path: Path) -> tuple[tuple[float, float], int, int]:
    try:
        w, h = int(cam["w"]), int(cam["h"])
        fx = float(cam["fl_x"])
        fy = float(cam.get("fl_y", fx))
    except (KeyError, TypeError, ValueError) as e:
        raise TnfError(f"{path}: camera intrinsics missing or malformed ({e}); rerun `tnf capture`") from None
    return (fx, fy), w, h


def _plain_json(x: Any) -> Any:
    from omegaconf import DictConfig, ListConfig, OmegaConf

    if isinstance(x, (DictConfig, ListConfig)):
        x = OmegaConf.to_container(x, resolve=True)
    return json.loads(json.dumps(x))


def _check_sensor(item: Any, name: str, config: dict[str, Any], obj: str) -> None:
    """The touches must come from the configured sensor with the same settings."""
    rec = item.manifest.get("sensor") or {}
    where = item.folder / "manifest.json"
    if rec.get("name") != name:
        raise TnfError(f"object {obj!r}: touches in {where} were made with sensor {rec.get('name')!r}, not {name!r}")
    got = _plain_json(rec.get("config", {}))
    for key in sorted(set(got) | set(config)):
        if got.get(key) != config.get(key):
            raise TnfError(
                f"object {obj!r}: sensor mismatch in {where}: {name}.{key} is {got.get(key)!r} there but "
                f"{config.get(key)!r} in this config; rerun `tnf touch` or use the same sensor settings"
            )


def _load_scene(kind: str, scene_dir: Path, source: Any, obj: str, device: str) -> Any:
    if kind == "fitted":
        from tnf.scenes import load_scene

        return load_scene(scene_dir, device)
    from tnf.registry import SCENES

    return SCENES.get("mesh").from_mesh(source.load(obj)).to(device)


def _write_previews(folder: Path, names: list[str], k: int, seed: int) -> None:
    """``previews/pair_XXXXX.png``: RGB | depth | background | tactile of ``k`` pairs (objects in turn), and the
    prior after the tactile image where the dataset holds it (``pair.prior``)."""
    import numpy as np
    from PIL import Image

    from tnf.data.store import open_pairs

    if k <= 0:
        return
    a = open_pairs(folder)
    rng = np.random.default_rng(seed)
    oid = np.asarray(a.object_id)
    picks: list[int] = []
    for j in range(k):
        rows = np.flatnonzero(oid == j % len(names))
        if len(rows):
            picks.append(int(rng.choice(rows)))
    out = folder / "previews"
    out.mkdir(exist_ok=True)
    for r in sorted(set(picks)):
        depth = (np.asarray(a.depth[r], np.float32) * 255).round().astype(np.uint8)
        panels = [a.rgb[r], np.repeat(depth[..., None], 3, -1), a.backgrounds[a.background_index[r]], a.tactile[r]]
        strip = np.concatenate(panels + ([a.prior[r]] if a.prior is not None else []), axis=1)
        Image.fromarray(strip).save(out / f"pair_{r:05d}_{names[oid[r]]}.png")


def _summary(console: Any, folder: Path, n: int, counts: dict[str, int], names: list[str], novel: list[str]) -> None:
    from rich.table import Table

    t = Table(title=f"paired dataset {folder}", box=None)
    t.add_column("split")
    t.add_column("pairs", justify="right")
    for s, c in counts.items():
        t.add_row(s, str(c))
    t.add_row("all", str(n))
    console.print(t)
    console.print(f"{len(names)} objects; novel objects: {', '.join(novel) or 'none'}")
