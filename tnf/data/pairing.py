"""Pair every touch with RGB-D rendered at its pose, and build a dataset under ``pairs/`` (``tnf pair``).

Two steps, both resumable: each object's touches are rendered and preprocessed into a cache item
(``pairs/.cache/<name>/<source>/<object>/``, skipped when done with the same settings), then the caches are
assembled into the dataset's memory-mapped arrays, chunk by chunk, with the split assignment. Every input is
checked before any rendering starts.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from tnf.artifacts import ArtifactStore, read_json
from tnf.data.forces import touch_forces
from tnf.data.preprocess import SIZE, crop_origin, gel_size_m
from tnf.data.prior import DepthPrior
from tnf.data.render import Framing, TouchItem, render_pairs_for_touches
from tnf.data.settings import PairSettings
from tnf.data.splits import SPLITS, assign_splits, choose_novel_objects
from tnf.data.store import PairWriter, open_pairs, write_manifest
from tnf.errors import TnfError
from tnf.registry import SCENES, SENSORS, config_to_dict, split_spec
from tnf.runtime import job_device, progress, resolve_device, stage_console, warp_device
from tnf.scenes import load_scene
from tnf.sim.base import simulator_key

ASSEMBLE_CHUNK = 256  # pairs copied per step while assembling (bounds memory)


@dataclass
class PairJob:
    """What ``tnf pair`` makes, built from the run's config by the stage.

    ``settings`` is the ``pair`` section; ``sensor``, ``scene``, ``simulator`` and ``objects`` are the config
    nodes of those groups as plain dicts; ``shard`` is ``(index, count)`` of a job in a sweep over object
    shards, or None for a run over every object (which also assembles the dataset).
    """

    settings: PairSettings
    name: str
    data_root: str
    source: Any
    names: list[str]
    sensor: dict[str, Any]
    scene: dict[str, Any]
    simulator: dict[str, Any] | None
    objects: dict[str, Any]
    touch_force: float
    seed: int
    device: str
    progress: bool
    shard: tuple[int, int] | None = None


def capture_camera(cam: dict[str, Any], path: Path) -> tuple[tuple[float, float], int, int]:
    """Focal lengths ``(fx, fy)`` in pixels and image size ``w, h`` of a capture's ``transforms.json`` (``cam``,
    read from ``path``). A missing or malformed field raises a one-line TnfError."""
    try:
        w, h = int(cam["w"]), int(cam["h"])
        fx = float(cam["fl_x"])
        fy = float(cam.get("fl_y", fx))
    except (KeyError, TypeError, ValueError) as e:
        raise TnfError(f"{path}: camera intrinsics missing or malformed ({e}); rerun `tnf capture`") from None
    return (fx, fy), w, h


def make_pairs(job: PairJob) -> None:
    """Render every selected object's touches into caches (this job's shard only), then assemble the dataset
    ``pairs/<job.name>/`` unless the job is one shard of a sweep."""
    p, store, names, src = job.settings, ArtifactStore(job.data_root), job.names, job.source.name
    sensor_name, sensor_params = split_spec(job.sensor, "sensor")
    sensor_cfg = SENSORS.config(sensor_name, sensor_params)
    sensor = SENSORS.get(sensor_name)(sensor_cfg)
    sensor_dict = _plain_json(config_to_dict(sensor_cfg))  # the dataset manifest's record, to rebuild the sensor
    device = job_device(resolve_device(job.device), job.shard)
    console = stage_console()

    inputs = _check_inputs(job, store, sensor.describe())
    framing = _framing(p, inputs, sensor)
    cache_keys = _cache_keys(job, inputs, framing)
    # A finished dataset made from the same inputs needs nothing, not even its (deleted) render caches.
    novel = choose_novel_objects(names, p.novel_objects, p.num_novel_objects, job.seed)
    dataset_key = {"objects": names, "novel_objects": novel, "caches": cache_keys, "source": src}
    touch_force = None
    if p.force:  # pair.force: each pair's touch force (force.npy), read from the touch manifests
        touch_force = touch_forces({o: inputs[o]["item"] for o in names})
        dataset_key["force"] = touch_force.record
    if store.is_done("pairs", job.name, config=dataset_key):
        console.print(f"pair: dataset {store.path('pairs', job.name)} is up to date")
        return
    # Every object's inputs decide the framing above; a job of a sweep over shards renders its share only.
    mine = names if job.shard is None else names[job.shard[0] :: job.shard[1]]
    todo = [o for o in mine if not store.is_done("pairs", ".cache", job.name, src, o, config=cache_keys[o])]
    _render_caches(job, store, todo, inputs, cache_keys, sensor, framing, device, console)
    if job.shard is not None:
        console.print(
            f"pair: shard {job.shard[0]} of {job.shard[1]}: {len(mine) - len(todo)} object(s) already rendered, "
            f"{len(todo)} rendered now; `tnf pair` without shard assembles the dataset"
        )
        return
    _assemble(job, store, inputs, novel, dataset_key, touch_force, framing, sensor_name, sensor_dict, console)


def _check_inputs(job: PairJob, store: Any, described: dict[str, Any]) -> dict[str, Any]:
    """Each object's touches, capture camera and fitted scene, checked before hours of rendering."""

    scene_name, src, sensor_name = str(job.scene["name"]), job.source.name, str(described["name"])
    inputs: dict[str, dict[str, Any]] = {}
    for obj in job.names:
        touch_dir = store.require(
            "touch", sensor_name, src, obj, hint=f"run `tnf touch object={obj} sensor={sensor_name}` first"
        )
        item = TouchItem.load(touch_dir)
        _check_sensor(item, described, obj)
        transforms = store.path("capture", src, obj) / "transforms.json"
        if not transforms.is_file():
            raise TnfError(f"object {obj!r}: capture not found ({transforms}); run `tnf capture object={obj}`")
        cam = read_json(transforms, "capture transforms")
        focal, w, h = capture_camera(cam, transforms)
        scene_dir = store.path("scenes", scene_name, src, obj)
        scene_hash = None
        if job.settings.scene_source == "fitted":
            if not (scene_dir / "scene.pt").is_file():
                raise TnfError(
                    f"object {obj!r} has touches but no fitted {scene_name} scene ({scene_dir}); "
                    f"run `tnf fit-scene object={obj} scene={scene_name}` first, or use pair.scene_source=mesh"
                )
            scene_hash = (store.manifest("scenes", scene_name, src, obj) or {}).get("config_hash")
        inputs[obj] = {"item": item, "focal": focal, "size": (w, h), "scene_dir": scene_dir, "scene_hash": scene_hash}
    return inputs


def _framing(p: PairSettings, inputs: dict[str, Any], sensor: Any) -> Any:
    """The crop and depth settings; the reference distance is the touches' median. Sets each input's
    ``crop_px`` (None for crops sized per view)."""
    import numpy as np

    distance = p.footprint_distance
    if distance is None:
        all_d = np.concatenate([i["item"].contact_distances() for i in inputs.values()])
        all_d = all_d[np.isfinite(all_d) & (all_d > 0)]
        if len(all_d):
            distance = float(np.median(all_d))
        elif p.crop_px is None:
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
    return framing


def _cache_keys(job: PairJob, inputs: dict[str, Any], framing: Any) -> dict[str, dict[str, Any]]:
    """What decides each object's render cache (its hash decides whether a finished cache is reused)."""

    p = job.settings
    cache_keys: dict[str, dict[str, Any]] = {}
    for obj, i in inputs.items():
        key = {
            "scene_source": p.scene_source,
            "scene": str(job.scene["name"]) if p.scene_source == "fitted" else "mesh",
            "scene_hash": i["scene_hash"],
            "touch_hash": i["item"].manifest.get("config_hash"),
            "touches": len(i["item"].touches),
            **dataclasses.asdict(framing),
            "crop_px": i["crop_px"],
            "focal": list(i["focal"]),
            "size": SIZE,
        }
        if p.prior:
            assert job.simulator is not None
            key["prior"] = _plain_json(simulator_key(job.simulator))
        if p.points:
            key["points"] = True
        cache_keys[obj] = key
    return cache_keys


def _render_caches(
    job: PairJob,
    store: Any,
    todo: list[str],
    inputs: dict[str, Any],
    cache_keys: dict[str, Any],
    sensor: Any,
    framing: Any,
    device: str,
    console: Any,
) -> None:
    """Step 1: render and preprocess the touches of the objects ``todo`` into their cache items."""
    import numpy as np

    p, src = job.settings, job.source.name
    optional = tuple(k for k in ("prior", "points") if getattr(p, k))
    n_render = sum(len(inputs[o]["item"].touches) for o in todo)
    if todo:
        console.print(f"pair: rendering {n_render} touches of {len(todo)} object(s) on {device} ({p.scene_source})")
    prior = None
    if p.prior:
        assert job.simulator is not None
        prior = DepthPrior(sensor, job.simulator, framing, device=warp_device(device))
        console.print(f"pair: with the prior, {job.simulator['name']}'s image of each depth crop (pair.prior)")
    with progress(job.progress) as bar:
        task = bar.add_task(f"render {job.name}", total=n_render)
        for obj in todo:
            i = inputs[obj]
            scene = _load_scene(p.scene_source, i["scene_dir"], job.source, obj, device)
            arrays = render_pairs_for_touches(
                scene,
                i["item"],
                sensor,
                framing,
                focal=i["focal"],
                device=device,
                render_batch=p.render_batch,
                render_chunk=p.render_chunk,
                on_batch=lambda k: bar.advance(task, k),
                with_points=p.points,
            )
            del scene
            if prior is not None:
                # Each touch's recorded force (imported touches may record none: touch.force then).
                forces = [t.force or float(job.touch_force) for t in i["item"].touches]
                arrays["prior"] = prior(arrays["depth"], np.asarray(forces, np.float32))
            labels = [t.split for t in i["item"].touches]
            assign_splits(labels, novel_object=False)  # validates the labels before caching
            with store.writing(
                "pairs", ".cache", job.name, src, obj, config=cache_keys[obj], info={"splits": labels}
            ) as tmp:
                for k in ("rgb", "depth", "tactile", "background", "touch_index", *optional):
                    np.save(tmp / f"{k}.npy", arrays[k])
            del arrays


def _assemble(
    job: PairJob,
    store: Any,
    inputs: dict[str, Any],
    novel: list[str],
    dataset_key: dict[str, Any],
    touch_force: Any,
    framing: Any,
    sensor_name: str,
    sensor_dict: dict[str, Any],
    console: Any,
) -> None:
    """Step 2: copy the caches into the dataset's arrays, chunk by chunk, with the split assignment."""
    import numpy as np

    p, names, src = job.settings, job.names, job.source.name
    optional = tuple(k for k in ("prior", "points") if getattr(p, k))
    assembled = optional + (("force",) if p.force else ())
    caches = {o: store.path("pairs", ".cache", job.name, src, o) for o in names}
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
    with store.writing("pairs", job.name, config=dataset_key) as tmp:
        start = 0
        with PairWriter(tmp, n, np.stack(backgrounds), optional=assembled) as writer:
            for oid, o in enumerate(names):
                labels = (store.manifest("pairs", ".cache", job.name, src, o) or {})["splits"]
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
        info = {"count": n, "counts": dict(split_counts), "counts_per_object": counts}
        _write_dataset_manifest(tmp, job, inputs, novel, touch_force, framing, sensor_name, sensor_dict, info)
        _write_previews(tmp, names, p.previews, job.seed)
    if not p.keep_cache:
        shutil.rmtree(store.path("pairs", ".cache", job.name), ignore_errors=True)
    _summary(console, store.path("pairs", job.name), n, split_counts, names, novel)


def _write_dataset_manifest(
    tmp: Path,
    job: PairJob,
    inputs: dict[str, Any],
    novel: list[str],
    touch_force: Any,
    framing: Any,
    sensor_name: str,
    sensor_dict: dict[str, Any],
    info: dict[str, Any],
) -> None:

    p, names = job.settings, job.names
    fitted = p.scene_source == "fitted"
    first = inputs[names[0]]["item"].manifest
    write_manifest(
        tmp,
        {
            "name": job.name,
            "objects": names,
            "sensors": [sensor_name],
            "novel_objects": novel,
            "count": info["count"],
            "counts": info["counts"],
            "counts_per_object": info["counts_per_object"],
            "object_source": _plain_json(job.objects),
            "sensor": {"name": sensor_name, "config": sensor_dict},
            "simulator": _plain_json(first.get("config", {}).get("simulator", job.simulator)),
            "touch_config_hashes": {o: inputs[o]["item"].manifest.get("config_hash") for o in names},
            "scene_source": p.scene_source,
            # pair.prior: the simulator that made prior.npy from the depth crops (tnf.data.prior).
            "prior": {"simulator": _plain_json(job.simulator)} if p.prior else None,
            # pair.points: points.npy holds each RGB-D pixel's surface point (tnf.data.render.crop_points).
            "points": {"frame": "object", "unit": "m"} if p.points else None,
            # pair.force: force.npy holds each pair's touch force; the touches' force range and bands.
            **({"force": touch_force.record} if touch_force is not None else {}),
            "scene": _plain_json(job.scene) if fitted else {"name": "mesh"},
            "scene_checkpoints": {o: (str(inputs[o]["scene_dir"] / "scene.pt") if fitted else None) for o in names},
            "scene_config_hashes": {o: inputs[o]["scene_hash"] for o in names},
            "preprocess": {
                **dataclasses.asdict(framing),
                "crop_px": {o: inputs[o]["crop_px"] for o in names if inputs[o]["crop_px"] is not None},
                "size": SIZE,
            },
        },
    )


def _plain_json(x: Any) -> Any:
    return json.loads(json.dumps(x))


def _check_sensor(item: Any, described: dict[str, Any], obj: str) -> None:
    """The touches of ``item`` must come from the configured sensor (``described``: its ``Sensor.describe()``)
    with the same settings and the same calibration's content."""
    name, config = described["name"], _plain_json(described["config"])
    rec = item.manifest.get("sensor") or {}
    where = item.folder / "manifest.json"
    if rec.get("name") != name:
        raise TnfError(f"object {obj!r}: touches in {where} were made with sensor {rec.get('name')!r}, not {name!r}")
    theirs, ours = rec.get("calibration_digest"), described.get("calibration_digest")
    if theirs != ours:
        said = {None: "no calibration"}
        raise TnfError(
            f"object {obj!r}: touches in {where} were made with {said.get(theirs, f'calibration {theirs}')}, this "
            f"config's {name} has {said.get(ours, f'calibration {ours}')}; rerun `tnf touch` or set the same "
            "sensor.calibration"
        )
    got = _plain_json(rec.get("config", {}))
    for key in sorted(set(got) | set(config)):
        if got.get(key) != config.get(key):
            raise TnfError(
                f"object {obj!r}: sensor mismatch in {where}: {name}.{key} is {got.get(key)!r} there but "
                f"{config.get(key)!r} in this config; rerun `tnf touch` or use the same sensor settings"
            )


def _load_scene(kind: str, scene_dir: Path, source: Any, obj: str, device: str) -> Any:
    if kind == "fitted":
        return load_scene(scene_dir, device)

    return SCENES.get("mesh").from_mesh(source.load(obj)).to(device)


def _write_previews(folder: Path, names: list[str], k: int, seed: int) -> None:
    """``previews/pair_XXXXX.png``: RGB | depth | background | tactile of ``k`` pairs (objects in turn), and the
    prior after the tactile image where the dataset holds it (``pair.prior``)."""
    import numpy as np
    from PIL import Image

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
