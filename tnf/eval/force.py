"""Evaluation by force, for a generator conditioned on the touch's force (docs/force.md).

On each test split, with each touch generated at its own (simulated) force:

- SSIM and MSE per force band (``train``, ``interpolation``, ``extrapolation``; ``tnf.sim.forces``), and on
  ``adjacent`` training forces (within one band width of the interpolation band: a press like the band's);
- the physical check: the contact area of each generated image against the simulator's image of the same touch
  (same pose, same force), as a Pearson correlation over the split's touches;
- the monotonic growth of contact area with force: each test pose generated at a sweep of forces from light to
  hard; the share of poses whose area never shrinks from one force to the next and is larger at the hardest
  than at the lightest.

Contact area (``contact_area``) is the share of an image's pixels that differ from the sensor's background by
more than a threshold (8-bit levels, mean over RGB): the same measure for simulated and generated images.

The figure (``sweep_figure``): one test pose at the sweep's forces, the simulator's image (pressed again at
each force) above the generator's.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np
import torch

from tnf.artifacts import MANIFEST, ArtifactStore, read_json
from tnf.data import PairDataset, collate_pairs
from tnf.data.preprocess import SIZE, resize_uint8
from tnf.data.render import TouchItem
from tnf.errors import TnfError
from tnf.eval.settings import EvaluateSettings
from tnf.metrics import mse, ssim
from tnf.registry import OBJECTS, SENSORS, SIMULATORS, split_spec
from tnf.runtime import warp_device
from tnf.sim.forces import BANDS, ForcePlan, check_force_value
from tnf.touches import TouchRecord


def contact_area(images: torch.Tensor, background: torch.Tensor, threshold: float) -> torch.Tensor:
    """[B] share of pixels in [0, 1] whose |image - background| (0-255 scale, mean over RGB) exceeds
    ``threshold``. ``images`` and ``background`` [B, 3, H, W] in [-1, 1] (``background`` may broadcast)."""
    diff = (images.float() - background.float().to(images.device)).abs().mean(1) * 127.5
    return (diff > threshold).float().mean((1, 2))


def pearson(a: Sequence[float], b: Sequence[float]) -> float | None:
    """Pearson correlation of two equally long sequences; None with fewer than 3 values or no spread."""
    x, y = np.asarray(a, np.float64), np.asarray(b, np.float64)
    if len(x) < 3 or x.std() == 0 or y.std() == 0:
        return None
    return float(np.corrcoef(x, y)[0, 1])


def monotonic(areas: np.ndarray) -> np.ndarray:
    """[P] bool: per pose (row of ``areas`` [P, S], forces ascending), the area never shrinks and is larger at
    the hardest force than at the lightest."""
    a = np.asarray(areas, np.float64)
    return (np.diff(a, axis=1) >= 0).all(1) & (a[:, -1] > a[:, 0])


def dataset_plan(manifest: Mapping[str, Any], where: Any) -> ForcePlan:
    """The force plan recorded in a dataset manifest; one-line TnfError when the dataset has no force."""
    rec = manifest.get("force")
    if not rec:
        raise TnfError(
            f"dataset {where} holds no touch forces; a model trained with force is evaluated on pairs made "
            "with pair.force=true"
        )
    if not rec.get("range"):
        raise TnfError(
            f"dataset {where}: its touches were pressed at one force (touch.force_range=null); evaluation by "
            "force needs touches made with a touch.force_range"
        )
    return ForcePlan.from_record(rec["range"])


def score_split(
    batches: Any,
    generate: Callable[[dict[str, torch.Tensor]], torch.Tensor],
    plan: ForcePlan,
    sweep: Sequence[float],
    threshold: float,
    on_batch: Callable[[], None] | None = None,
) -> dict[str, Any]:
    """Band metrics, area correlation and monotonic share of one split (see the module's docstring).

    Returns ``{"bands": {band: {ssim, mse, n}}, "area": {r, n, generated_mean, simulated_mean},
    "monotonic": {share, n}, "rows": [(object_id, touch row in the batch order, force)]}``."""
    per: dict[str, dict[str, list[float]]] = {b: {"ssim": [], "mse": []} for b in (*BANDS, "adjacent", "outside")}
    a_fake: list[float] = []
    a_real: list[float] = []
    mono: list[bool] = []
    with torch.no_grad():
        for batch in batches:
            real = batch["tactile"]
            force = batch["force"].float()
            bg = batch["background"]
            fake = generate(batch).detach().float().to(real.device)
            s, m = ssim(fake, real).tolist(), mse(fake, real).tolist()
            near = plan.adjacent(force.tolist())
            for band, si, mi, ni in zip(plan.band_of(force.tolist()), s, m, near, strict=True):
                for b in (band, "adjacent") if ni else (band,):
                    per[b]["ssim"].append(si)
                    per[b]["mse"].append(mi)
            a_fake += contact_area(fake, bg, threshold).tolist()
            a_real += contact_area(real, bg, threshold).tolist()
            areas = []
            for f in sweep:
                g = generate({**batch, "force": torch.full_like(force, float(f))}).detach().float()
                areas.append(contact_area(g, bg, threshold).cpu().numpy())
            mono += monotonic(np.stack(areas, 1)).tolist()
            if on_batch is not None:
                on_batch()

    def mean(v: list[float]) -> float | None:
        return sum(v) / len(v) if v else None

    bands = {
        b: {"ssim": mean(v["ssim"]), "mse": mean(v["mse"]), "n": len(v["ssim"])}
        for b, v in per.items()
        if v["ssim"] or b not in ("outside",)
    }
    r = pearson(a_fake, a_real)
    return {
        "bands": bands,
        "area": {
            "r": r,
            "n": len(a_fake),
            "generated_mean": mean(a_fake),
            "simulated_mean": mean(a_real),
        },
        "monotonic": {"share": mean([float(x) for x in mono]), "n": len(mono)},
    }


def resimulate(
    sensor: Any, simulator: Any, mesh: Any, start_c2w: np.ndarray, forces: Sequence[float], size: int
) -> np.ndarray:
    """The simulator's images of one start pose pressed at each of ``forces`` (newtons), as the datasets store
    them: uint8 [S, size, size, 3] (resized like ``tnf pair``'s tactile images)."""

    poses = np.repeat(np.asarray(start_c2w, np.float64)[None], len(forces), 0)
    out = simulator.press(mesh, poses, np.asarray(forces, np.float32), seed=0)
    if not bool(np.all(out.hit)):
        raise TnfError("the figure's touch pose no longer reaches its object when pressed again")
    return resize_uint8(out.images, size)


def sweep_figure(
    simulated: np.ndarray, generated: np.ndarray, forces: Sequence[float], title: str
) -> Any:  # PIL.Image.Image
    """One pose at ``forces``: the simulator's images (uint8 [S, H, W, 3]) in the top row, the generator's below,
    each column labelled with its force."""
    from PIL import Image, ImageDraw, ImageFont

    s, h, w = simulated.shape[:3]
    pad, label_w, head = 4, 70, 16
    img = Image.new("RGB", (label_w + s * (w + pad), head + 2 * (h + pad) + 14), "white")
    draw = ImageDraw.Draw(img)
    font = ImageFont.load_default()
    draw.text((2, 2), title, fill="black", font=font)
    for row, (name, images) in enumerate((("simulator", simulated), ("generated", generated))):
        y = head + row * (h + pad)
        draw.text((2, y + h // 2 - 5), name, fill="black", font=font)
        for j in range(s):
            img.paste(Image.fromarray(images[j]), (label_w + j * (w + pad), y))
    for j, f in enumerate(forces):
        draw.text((label_w + j * (w + pad) + 2, head + 2 * (h + pad)), f"{f:g} N", fill="black", font=font)
    return img


def fmt(x: float | None, digits: int = 4) -> str:
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.{digits}f}"


def by_force(
    settings: EvaluateSettings,
    seed: int,
    pairs: Any,
    object_names: Sequence[str] | None,
    generate: Callable[[dict[str, torch.Tensor]], torch.Tensor],
    device: str,
    bar: Any,
    *,
    data_root: str,
    objects: Mapping[str, Any],
    simulator: Mapping[str, Any],
) -> tuple[dict[str, Any], bytes]:
    """Evaluation by force of a force-conditioned model on the test splits of dataset ``pairs`` (a folder):
    ``({"plan", "sweep", "area_threshold", <split>: score_split(...), "figure": {...}}, figure PNG bytes)``.
    ``generate`` makes the model's images of a batch (its ``force`` key, newtons, sets the press).

    ``settings`` is the ``evaluate`` section; ``objects`` and ``simulator`` are the config nodes of those groups
    (the figure's touch is pressed again on the object's mesh, under ``data_root``)."""
    import functools
    import io

    from torch.utils.data import DataLoader

    bf = settings.by_force
    manifest = read_json(pairs / MANIFEST, "dataset manifest")
    plan = dataset_plan(manifest, pairs)
    sweep = [check_force_value(f, "evaluate.by_force.sweep") for f in (bf.sweep or plan.sweep(6))]
    if len(sweep) < 2 or any(b <= a for a, b in zip(sweep, sweep[1:], strict=False)):
        raise TnfError(f"evaluate.by_force.sweep must hold at least two forces in ascending order, got {sweep}")
    sensor_name = str(manifest["sensor"]["name"])
    sensor = SENSORS.get(sensor_name)(SENSORS.config(sensor_name, manifest["sensor"]["config"]))
    for f in sweep:  # before any scoring: the simulator presses the figure's touch at each
        sensor.check_force(f, "evaluate.by_force.sweep")
    threshold = bf.area_threshold
    out: dict[str, Any] = {"plan": plan.describe(), "sweep": sweep, "area_threshold": threshold}
    splits = list(settings.splits)
    for split in splits:
        ds = PairDataset(pairs, splits=[split], per_object=settings.per_object, seed=seed, object_names=object_names)
        loader = DataLoader(ds, batch_size=settings.batch_size, shuffle=False, collate_fn=collate_pairs)
        task = bar.add_task(f"by force {split}", total=len(loader))
        out[split] = score_split(
            loader, generate, plan, sweep, threshold, on_batch=functools.partial(bar.advance, task)
        )

    # The figure: the figure split's first touch that shows a contact, pressed again at each force of the sweep.
    split = bf.figure_split if bf.figure_split in splits else splits[0]
    ds = PairDataset(pairs, splits=[split], per_object=settings.per_object, seed=seed, object_names=object_names)
    batch = ds.__getitems__(list(range(min(len(ds), 64))))
    areas = contact_area(batch["tactile"], batch["background"], threshold)
    row = int(torch.argmax((areas > 0).float()))  # the first with a contact (0 when none has one)
    obj = ds.arrays.objects[int(ds.arrays.object_id[ds.index[row]])]
    touch_index = int(ds.arrays.touch_index[ds.index[row]])
    source = OBJECTS.build(objects)
    source.name = split_spec(objects, "objects")[0]
    store = ArtifactStore(data_root)
    touch = _touch(store, sensor_name, source.name, obj, touch_index)
    sim = SIMULATORS.build(simulator, sensor=sensor, device=warp_device(device))
    simulated = resimulate(sensor, sim, source.load(obj), np.asarray(touch.start_c2w), sweep, SIZE)
    n_ref = min(bf.simulator_poses, len(ds))
    if n_ref > 0:
        out["simulator_monotonic"] = _simulator_monotonic(ds, n_ref, sim, source, store, sensor_name, sweep, threshold)
    one = {k: v[row : row + 1] for k, v in batch.items()}
    generated, sweep_areas = _sweep_of_one(one, generate, simulated, sweep, threshold)
    out["figure"] = {"split": split, "object": obj, "touch": touch_index, **sweep_areas}
    img = sweep_figure(simulated, generated, sweep, f"{obj}, touch {touch_index} ({split})")
    buf = io.BytesIO()
    img.save(buf, "PNG")
    return out, buf.getvalue()


def _simulator_monotonic(
    ds: Any,
    n_ref: int,
    sim: Any,
    source: Any,
    store: Any,
    sensor_name: str,
    sweep: list[float],
    threshold: float,
) -> dict[str, Any]:
    """The simulator's own growth with force on the first ``n_ref`` poses of ``ds`` (a ``PairDataset``): what the
    generator's is measured against (a pose the simulator does not grow on cannot be asked of the generator).

    Each pose is pressed again at every force of ``sweep`` (newtons); returns ``{"share": the share of the poses
    that hit at every force whose contact area grows with force (None without such poses), "n": their count}``."""
    ref = ds.__getitems__(list(range(n_ref)))
    starts: dict[str, list[tuple[int, np.ndarray]]] = {}
    for i in range(n_ref):
        o = ds.arrays.objects[int(ds.arrays.object_id[ds.index[i]])]
        touch = _touch(store, sensor_name, source.name, o, int(ds.arrays.touch_index[ds.index[i]]))
        starts.setdefault(o, []).append((i, np.asarray(touch.start_c2w)))
    ref_areas = np.zeros((n_ref, len(sweep)))
    hit = np.ones(n_ref, bool)
    for o, poses in starts.items():
        c2w = np.repeat(np.stack([p for _, p in poses]), len(sweep), 0)
        press = sim.press(source.load(o), c2w, np.tile(np.asarray(sweep, np.float32), len(poses)), seed=0)
        img = torch.from_numpy(resize_uint8(press.images, SIZE)).permute(0, 3, 1, 2).float() / 127.5 - 1
        a = contact_area(img, ref["background"][:1], threshold).numpy().reshape(len(poses), len(sweep))
        for j, (i, _) in enumerate(poses):
            ref_areas[i] = a[j]
            hit[i] = bool(press.hit[j * len(sweep) : (j + 1) * len(sweep)].all())
    grows = monotonic(ref_areas[hit])
    return {"share": float(grows.mean()) if len(grows) else None, "n": int(hit.sum())}


def _sweep_of_one(
    one: dict[str, torch.Tensor],
    generate: Callable[[dict[str, torch.Tensor]], torch.Tensor],
    simulated: np.ndarray,
    sweep: list[float],
    threshold: float,
) -> tuple[np.ndarray, dict[str, list[float]]]:
    """The generator's images of the one-pair batch ``one`` at each force of ``sweep`` (newtons): [F, H, W, 3]
    uint8, and the contact areas of them and of the simulator's ``simulated`` ones ([F, H, W, 3] uint8) at each
    force (``{"simulated_area": [F], "generated_area": [F]}``)."""
    many = {k: v.expand(len(sweep), *v.shape[1:]) for k, v in one.items()}
    many["force"] = torch.tensor(sweep, dtype=torch.float32)
    with torch.no_grad():
        fake = generate(many).detach().float().cpu()
    generated = ((fake.clamp(-1, 1) + 1) * 127.5).round().to(torch.uint8).permute(0, 2, 3, 1).numpy()
    bg = one["background"]
    sim_t = torch.from_numpy(simulated).permute(0, 3, 1, 2).float() / 127.5 - 1
    areas = {
        "simulated_area": contact_area(sim_t, bg, threshold).tolist(),
        "generated_area": contact_area(fake, bg, threshold).tolist(),
    }
    return generated, areas


def _touch(store: Any, sensor: str, source: str, obj: str, index: int) -> TouchRecord:
    """Touch ``index`` of an object's touch item (its record: start pose, force...)."""

    item = TouchItem.load(store.require("touch", sensor, source, obj, hint="run `tnf touch` first"))
    return next(t for t in item.touches if t.index == index)
