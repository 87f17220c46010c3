"""Fine-tuning a generator on real indenter presses: the paper's few-shot transfer (Section 4.2, Table 2) with
real frames in place of a second simulated sensor.

A press pair is what a touch pair is (``tnf.data.store``): the input is the indenter rendered as RGB-D at the
press's pose (``tnf.real.generated.press_rgbd``) and the presses' real background, the target the real frame,
both resized from the sensor's size to 128 px as the pairing stage resizes tactile images. :func:`write_press_pairs`
writes such a dataset (optionally with simulated training pairs mixed in: T-N+); :func:`finetune_on_presses`
trains on it through the Lightning path of ``tnf finetune`` (``GeneratorSystem``, ``tnf.generators.training.fit``),
from a checkpoint or from scratch; :func:`write_press_realism` scores a checkpoint on held-out presses.
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
import shutil
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from tnf.data.preprocess import SIZE, resize_uint8
from tnf.data.render import Framing
from tnf.data.splits import SPLITS
from tnf.data.store import PairWriter, open_pairs, write_manifest
from tnf.errors import TnfError
from tnf.real import report
from tnf.real.generated import (
    REFERENCES,
    checkpoint_framing,
    generate_presses,
    press_rgbd,
)
from tnf.real.presses import PressSet, at_sensor_size, presses_digest
from tnf.sensors.base import Sensor

PRESS_OBJECT = "indenter"
"""The object name of press pairs in a dataset's ``objects``."""
CPU_TRAINER = {"accelerator": "cpu", "devices": 1, "precision": "32-true", "strategy": "auto"}
"""Lightning Trainer arguments of :func:`finetune_on_presses` by default (``conf/trainer/cpu.yaml``)."""


def check_split(train: Sequence[int], val: Sequence[int] = (), test: Sequence[int] = (), where: str = "") -> None:
    """A one-line TnfError unless ``train`` is non-empty and ``train``, ``val`` and ``test`` share no press."""
    prefix = f"{where}: " if where else ""
    if not train:
        raise TnfError(f"{prefix}fine-tuning needs at least one training press")
    for name, other in (("validation", val), ("test", test)):
        both = sorted(set(train) & set(other))
        if both:
            raise TnfError(f"{prefix}press {both[0]} is both a training and a {name} press")
    both = sorted(set(val) & set(test))
    if both:
        raise TnfError(f"{prefix}press {both[0]} is both a validation and a test press")


def write_press_pairs(
    presses: PressSet,
    sensor: Sensor,
    train: Sequence[int],
    out: str | Path,
    *,
    val: Sequence[int] = (),
    depth_scale: float = 1.0,
    framing: Framing | None = None,
    reference: str = "gel",
    sim: str | Path | None = None,
    sim_pairs: int = 0,
    seed: int = 0,
    device: str = "cpu",
) -> dict[str, Any]:
    """Write a paired dataset (``tnf.data.store``'s format) of real presses into the folder ``out``.

    Args:
        presses: a checked press folder.
        sensor: the sensor the frames are resized to (its size and pixel geometry must match the recording's).
        train: presses of the ``train`` split.
        out: the dataset folder (created; its arrays are replaced).
        val: presses of the ``val`` split; none: the training presses serve as validation pairs too.
        depth_scale: factor on each press's depth (the calibration's depth factor).
        framing: the crop and depth settings of the generator's data (``checkpoint_framing``).
        reference: where depth 0.5 lies (``tnf.real.generated``: ``gel`` or ``contact``).
        sim: a simulated paired dataset to take ``sim_pairs`` training pairs from (T-N+); None: none.
        sim_pairs: how many of ``sim``'s training pairs join the ``train`` split, drawn with ``seed``.
        seed: seed of that draw.
        device: torch device to render on.

    Returns:
        The dataset's manifest fields (``count``, ``counts``, ``presses``, ``sim``).
    """
    check_split(list(train), list(val))
    if sim_pairs < 0 or (sim_pairs and sim is None):
        raise TnfError(f"sim_pairs={sim_pairs} needs a simulated dataset to draw from (and a count >= 0)")
    framing = (framing or Framing()).with_sensor(sensor)
    rows, backgrounds = _press_rows(presses, sensor, list(train), list(val), depth_scale, framing, reference, device)
    objects = [PRESS_OBJECT]
    sim_record = None
    if sim_pairs:
        assert sim is not None
        rows, sim_record = _with_sim_pairs(rows, backgrounds, objects, Path(sim), sim_pairs, seed)
    out = Path(out)
    n = len(rows["rgb"])
    with PairWriter(out, n, np.stack(backgrounds)) as writer:
        writer.write(0, **rows)
    codes = rows["split"]
    counts = {s: int((codes == i).sum()) for i, s in enumerate(SPLITS)}
    record = {
        "folder": str(presses.folder),
        "digest": presses_digest(presses),
        "train": list(train),
        "val": list(val),
        "val_from_train": not val,
        "radius_mm": presses.radius_mm,
        "depth_scale": float(depth_scale),
        "reference": reference,
    }
    info = {"count": n, "counts": counts, "presses": record, "sim": sim_record}
    write_manifest(out, _press_manifest(out.name, objects, sensor, presses.radius_mm, framing, info))
    return info


def _press_rows(
    presses: PressSet,
    sensor: Sensor,
    train: list[int],
    val: list[int],
    depth_scale: float,
    framing: Framing,
    reference: str,
    device: str,
) -> tuple[dict[str, np.ndarray], list[np.ndarray]]:
    """The pair arrays of presses ``train`` then ``val`` (the training presses again when ``val`` is empty):
    RGB-D of the indenter at each press, the real frames at 128 px, and the backgrounds list."""
    val_rows = val or train
    indices = train + val_rows
    sp = at_sensor_size(presses, sensor, indices)
    radius = presses.radius_mm * 1e-3
    views = press_rgbd(sensor, sp, radius, depth_scale, framing=framing, reference=reference, device=device)
    split = np.array([SPLITS.index("train")] * len(train) + [SPLITS.index("val")] * len(val_rows), np.int8)
    rows = {
        "rgb": views.rgb,
        "depth": views.depth,
        "tactile": resize_uint8(sp.frames, SIZE),
        "background_index": np.zeros(len(indices), np.int32),
        "object_id": np.zeros(len(indices), np.int32),
        "split": split,
        "touch_index": np.asarray(indices, np.int32),
        "sensor_id": np.zeros(len(indices), np.int16),
    }
    return rows, [resize_uint8(sp.background, SIZE)]


def _press_manifest(
    name: str, objects: list[str], sensor: Sensor, radius_mm: float, framing: Framing, info: dict[str, Any]
) -> dict[str, Any]:
    """The manifest of a press dataset: a paired dataset whose scene is the indenter (a sphere of
    ``radius_mm``) rendered with the mesh scene."""
    return {
        "name": name,
        "objects": objects,
        "sensors": [sensor.name],
        "novel_objects": [],
        **info,
        "sensor": sensor.describe(),
        "scene_source": "mesh",
        "scene": {"name": "mesh", "indenter": {"shape": "sphere", "radius_mm": radius_mm}},
        "preprocess": {**dataclasses.asdict(framing), "crop_px": {}, "size": SIZE},
    }


def _with_sim_pairs(
    rows: dict[str, np.ndarray], backgrounds: list[np.ndarray], objects: list[str], sim: Path, k: int, seed: int
) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """``rows`` with ``k`` training pairs of the simulated dataset ``sim`` appended to the ``train`` split
    (their objects and backgrounds added to ``objects`` and ``backgrounds``)."""
    a = open_pairs(sim)
    pool = np.flatnonzero(np.asarray(a.split) == SPLITS.index("train"))
    if len(pool) < k:
        raise TnfError(f"{sim} has {len(pool)} training pairs; {k} were asked for (sim_pairs)")
    pick = np.sort(np.random.default_rng(seed).choice(pool, size=k, replace=False))
    bg_map = []
    for bg in np.asarray(a.backgrounds):
        same = [j for j, b in enumerate(backgrounds) if np.array_equal(b, bg)]
        if not same:
            backgrounds.append(np.asarray(bg))
        bg_map.append(same[0] if same else len(backgrounds) - 1)
    obj_map = []
    for name in a.objects:
        if name not in objects:
            objects.append(name)
        obj_map.append(objects.index(name))
    added = {
        "rgb": np.asarray(a.rgb[pick]),
        "depth": np.asarray(a.depth[pick]),
        "tactile": np.asarray(a.tactile[pick]),
        "background_index": np.asarray(bg_map, np.int32)[np.asarray(a.background_index[pick])],
        "object_id": np.asarray(obj_map, np.int32)[np.asarray(a.object_id[pick])],
        "split": np.full(k, SPLITS.index("train"), np.int8),
        "touch_index": np.asarray(a.touch_index[pick], np.int32),
        "sensor_id": np.zeros(k, np.int16),
    }
    merged = {key: np.concatenate([rows[key], added[key]]) for key in rows}
    return merged, {"dataset": str(sim), "pairs": int(k), "rows": pick.tolist()}


def _check_finetune(reference: str, steps: Any, batch_size: int, train: Sequence[int], val: Sequence[int]) -> None:
    """One-line TnfErrors for ``finetune_on_presses``' arguments."""
    if reference not in REFERENCES:
        raise TnfError(f"reference must be one of {', '.join(REFERENCES)}, got {reference!r}")
    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
        raise TnfError(f"steps must be a whole number >= 1, got {steps!r}")
    if batch_size < 1:
        raise TnfError(f"batch_size must be >= 1, got {batch_size}")
    check_split(list(train), list(val))


def _start_system(
    ckpt: Path | None, generator: Mapping[str, Any] | None, lr: float | None, epochs: int, ema_decay: float | None
) -> tuple[Any, dict[str, Any]]:
    """The ``GeneratorSystem`` to fine-tune for ``epochs`` (the checkpoint's weights with fresh optimisers, or
    ``generator`` from scratch) and the record of where it started."""
    from tnf.generators.system import GeneratorSystem

    hp: dict[str, Any] = {
        "epochs": epochs,
        "decay_epochs": epochs // 2,
        "grid_rows": 4,
        "finite_check_every": 50,
        "ema_decay": ema_decay,
    }
    overrides = {"lr": float(lr)} if lr is not None else {}
    if ckpt is None:
        return GeneratorSystem({**dict(generator or {"name": "tn_cgan"}), **overrides}, **hp), {}
    system = GeneratorSystem.from_checkpoint(ckpt, "cpu", generator_overrides=overrides, **hp)
    return system, {"checkpoint": str(ckpt.resolve()), "checkpoint_hash": file_hash(ckpt)}


def finetune_on_presses(
    checkpoint: str | Path | None,
    presses: PressSet,
    sensor: Sensor,
    train: list[int],
    out: Path,
    steps: int,
    *,
    val: Sequence[int] = (),
    lr: float | None = None,
    batch_size: int = 16,
    generator: Mapping[str, Any] | None = None,
    framing: Framing | None = None,
    depth_scale: float = 1.0,
    reference: str = "gel",
    sim: str | Path | None = None,
    sim_pairs: int = 0,
    freeze: Sequence[str] = (),
    ema_decay: float | None = None,
    seed: int = 0,
    trainer: Mapping[str, Any] | None = None,
    progress: bool = False,
    val_every_n_epochs: int = 1,
) -> Path:
    """Fine-tune a generator on the real frames of presses ``train``; returns the new checkpoint
    (``out/last.ckpt``: the weights after ``steps`` training batches).

    The run folder ``out`` is a model run as ``tnf finetune`` writes one (``last.ckpt``, ``best.ckpt`` by the
    validation pairs' L1, ``metrics.csv``, ``grids/``, ``manifest.json``) with its press dataset in
    ``out/pairs/``. ``checkpoint`` None trains ``generator`` (a spec ``{"name": ..., ...}``; default
    ``tn_cgan``'s defaults) from scratch; otherwise the checkpoint's generator starts from its weights with
    fresh optimisers, and the checkpoint is not modified.

    Args:
        steps: training batches; rounded up to whole epochs of ``ceil(pairs / batch_size)`` batches. The
            learning rate is constant for the first half of the epochs, then decays linearly toward zero.
        val: validation presses (``best.ckpt`` follows their L1); none: the training presses.
        lr: the generator's learning rate; None keeps its own.
        framing: the crop and depth settings; default the checkpoint's training data's
            (``checkpoint_framing``), or ``Framing()`` from scratch.
        depth_scale, reference: as :func:`write_press_pairs`.
        sim, sim_pairs: simulated training pairs mixed in (T-N+), as :func:`write_press_pairs`.
        freeze: parameter-name prefixes kept fixed (``finetune.freeze``).
        ema_decay: keep an exponential moving average of the weights (``finetune.ema_decay``).
        trainer: Lightning Trainer arguments; default :data:`CPU_TRAINER`.
        progress: show Lightning's progress bar.
        val_every_n_epochs: validate (``best.ckpt``, the image grid) after every this many epochs.
    """
    from tnf.data import PairDataModule
    from tnf.generators.training import fit
    from tnf.runtime import seed_everything

    _check_finetune(reference, steps, batch_size, train, val)
    out = Path(out)
    ckpt = Path(checkpoint) if checkpoint is not None else None
    if ckpt is not None and not ckpt.is_file():
        raise TnfError(f"checkpoint not found: {ckpt}")
    if framing is None:
        framing = checkpoint_framing(ckpt) if ckpt is not None else Framing()
    epochs = max(1, math.ceil(steps / math.ceil((len(train) + int(sim_pairs)) / batch_size)))
    system, source = _start_system(ckpt, generator, lr, epochs, ema_decay)
    frozen = system.generator.freeze([str(x) for x in freeze]) if freeze else []
    config = {
        "generator": dict(system.hparams["generator"]), "source": source,
        "presses": {"folder": str(presses.folder), "digest": presses_digest(presses)},
        "train": list(train), "val": list(val), "steps": int(steps), "batch_size": int(batch_size), "lr": lr,
        "sensor": sensor.describe(), "framing": dataclasses.asdict(framing.with_sensor(sensor)),
        "depth_scale": float(depth_scale), "reference": reference,
        "sim": {"dataset": str(sim), "pairs": int(sim_pairs)} if sim_pairs else None,
        "freeze": list(freeze), "ema_decay": ema_decay, "seed": int(seed),
        "val_every_n_epochs": int(val_every_n_epochs),
    }  # fmt: skip
    pairs = out / "pairs"
    if pairs.exists():
        shutil.rmtree(pairs)
    record = write_press_pairs(
        presses, sensor, train, pairs, val=val, depth_scale=depth_scale, framing=framing, reference=reference,
        sim=sim, sim_pairs=sim_pairs, seed=seed,
    )  # fmt: skip
    seed_everything(int(seed))
    dm = PairDataModule([pairs], batch_size=batch_size, seed=int(seed), convert_on_device=True)
    info = {
        "generator": system.hparams["generator"]["name"], "datasets": [str(pairs)], "source": source,
        "frozen": frozen, "object_names": dm.object_names, "presses": record["presses"],
    }  # fmt: skip
    fit(
        system, dm, out, config=config, trainer_cfg=dict(trainer or CPU_TRAINER), logger_cfg={"name": "csv"},
        resume=True, progress=progress, log_every_n_steps=1, checkpoint_every_s=60.0,
        val_every_n_epochs=val_every_n_epochs, info=info,
    )  # fmt: skip
    return out / "last.ckpt"


def write_press_realism(
    checkpoint: str | Path,
    presses: PressSet,
    sensor: Sensor,
    test: Sequence[int],
    out: str | Path,
    *,
    framing: Framing | None = None,
    depth_scale: float = 1.0,
    reference: str = "gel",
    region_scale: float = 1.5,
    crop_scale: float = 4.0,
    seed: int = 0,
    label: str = "generated",
) -> dict[str, Any]:
    """Generate the presses ``test`` with ``checkpoint`` (``generate_presses``) and write the realism report of
    those images against the real frames (:func:`tnf.real.report.write_report`: ``out/realism.md``, ``.json``,
    ``.png``). Returns its record (``per_press``, ``mean``, seconds per frame) with the settings added."""
    if not test:
        raise TnfError("no test presses to score")
    sp = at_sensor_size(presses, sensor, list(test))
    t0 = time.perf_counter()
    images = generate_presses(
        checkpoint, sensor, sp, presses.radius_mm * 1e-3, depth_scale, framing=framing, reference=reference, seed=seed
    )
    row = report.Row(label, images, (time.perf_counter() - t0) / len(test))
    intro = [
        f"Checkpoint {checkpoint}: its touches of the indenter at each held-out press, {sensor.width}x"
        f"{sensor.height}, against the real frames of presses {list(test)}."
    ]
    settings = {"checkpoint": str(checkpoint), "depth_scale": float(depth_scale), "reference": reference}
    return report.write_report(
        out, "Generated presses against real frames", intro, [row], presses, sp,
        crop_scale=crop_scale, region_scale=region_scale, extra=settings,
    )  # fmt: skip


def file_hash(path: str | Path) -> str:
    """A short SHA-256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()[:16]
