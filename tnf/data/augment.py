"""Augmenting training pairs: the sensor's mirror symmetry (whole pairs flipped left-right), a shift of the contact
across the gel, and jitter of the RGB image's brightness and contrast."""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from typing import Any, Literal, overload

import torch

from tnf.data.settings import AUGMENTATIONS
from tnf.errors import TnfError
from tnf.registry import SENSORS

log = logging.getLogger(__name__)

Batch = dict[str, torch.Tensor]
"""A batch of pairs: key -> ``[B, ...]`` tensor."""


def check_augment(augment: Sequence[str] | None) -> tuple[str, ...]:
    """``data.augment`` as a tuple of known augmentation names (a TnfError for anything else)."""
    if augment is None:
        return ()
    if isinstance(augment, (bool, str)):
        raise TnfError(f"data.augment is a list of augmentations from {list(AUGMENTATIONS)}, got {augment!r}")
    names = tuple(str(a) for a in augment)
    unknown = [a for a in names if a not in AUGMENTATIONS]
    if unknown:
        raise TnfError(f"unknown augmentation {unknown[0]!r} in data.augment; known: {', '.join(AUGMENTATIONS)}")
    return names


@overload
def sensor_mirror(manifest: dict[str, Any], where: Any, required: Literal[True] = ...) -> tuple[int, ...]: ...


@overload
def sensor_mirror(manifest: dict[str, Any], where: Any, required: bool) -> tuple[int, ...] | None: ...


def sensor_mirror(manifest: dict[str, Any], where: Any, required: bool = True) -> tuple[int, ...] | None:
    """The mirror symmetry (``Sensor.mirror_channels``) of the sensor a dataset was made with, from the sensor
    record ``tnf pair`` writes into its manifest; a TnfError when there is no record, or no symmetry and
    ``required`` (else None)."""

    rec = manifest.get("sensor")
    if not isinstance(rec, dict) or not isinstance(rec.get("name"), str):
        raise TnfError(
            f"dataset {where} does not record its sensor's settings, which the sensor's mirror needs "
            "(data.augment=[mirror], generate.mirror_average); rebuild it with `tnf pair`"
        )
    sensor = SENSORS.build({"name": rec["name"], **(rec.get("config") or {})})
    channels = sensor.mirror_channels()
    if channels is None and required:
        raise TnfError(
            f"sensor {rec['name']!r} of dataset {where} has no mirror symmetry (its gel, lights or markers are "
            "not left-right mirror images up to a swap of colour channels); drop 'mirror' from data.augment"
        )
    return channels


def mirror_augment(
    augment: tuple[str, ...], datasets: Sequence[tuple[dict[str, Any], Any]]
) -> tuple[tuple[str, ...], tuple[int, ...] | None]:
    """``augment`` and the channel order its ``mirror`` uses (None without ``mirror``), for the datasets given as
    (manifest, where) pairs: their sensors' common mirror symmetry. Where their sensor has none (the OmniTact),
    ``mirror`` is left out with a warning, as ``generate.mirror_average`` generates such a sensor's images as they
    are, so that one experiment config serves every sensor. Datasets whose sensors mirror differently, or of which
    only some mirror, are a TnfError: a batch cannot mix them."""
    if "mirror" not in augment:
        return augment, None
    orders = {sensor_mirror(manifest, where, required=False) for manifest, where in datasets}
    if len(orders) > 1:
        none = "; None: no mirror symmetry" if None in orders else ""
        raise TnfError(
            "data.augment=[mirror] needs datasets whose sensors mirror alike, but their channel orders differ "
            f"({', '.join(sorted(map(str, orders)))}{none}); train on them without it"
        )
    order = orders.pop()
    if order is None:
        sensors = sorted({str(manifest["sensor"]["name"]) for manifest, _ in datasets})
        log.warning(
            "sensor %s has no mirror symmetry (its gel, lights or markers are not left-right mirror images up to a "
            "swap of colour channels): training without data.augment's mirror",
            ", ".join(sensors),
        )
        return tuple(a for a in augment if a != "mirror"), None
    return augment, order


MIRRORED_IMAGES = ("rgb", "depth", "background", "tactile", "prior", "points")
"""Batch keys that the mirror flips left-right; the sensor's images (``SENSOR_IMAGES``) also reorder channels.
The surface points flip with the image and keep their values: the mirrored pair is a touch of the mirrored
object, whose surface point under a pixel is the mirror image of the object's own."""


SENSOR_IMAGES = ("background", "tactile", "prior")
"""Batch keys holding the sensor's own images (``prior``: the simulator's image of the depth, ``tnf.data.prior``)."""


def mirror_batch(batch: Mapping[str, torch.Tensor], mirror: Sequence[int]) -> Batch:
    """Every image of ``batch`` (those of ``MIRRORED_IMAGES`` it holds, [B, C, H, W]) as the sensor sees the
    mirrored object: flipped left-right, the sensor's images with their channels in the order ``mirror``
    (``Sensor.mirror_channels``). New tensors; other keys are left out."""
    out = {}
    for k in MIRRORED_IMAGES:
        if k not in batch:
            continue
        x = batch[k].flip(-1)
        if k in SENSOR_IMAGES:
            x = x.index_select(1, torch.tensor(list(mirror), device=x.device))
        out[k] = x
    return out


SHIFTED_IMAGES = ("rgb", "depth", "points")
"""Batch keys that the shift moves as they are; the sensor's press images (``tactile``, ``prior``) move as their
change from ``background``, which stays: the gel and its lights do not move with the contact."""


def shift_batch(batch: Mapping[str, torch.Tensor], frac: torch.Tensor) -> Batch:
    """Every image of ``batch`` moved sideways by ``frac`` ([B, 2], x then y, each a fraction of the image's
    half-width and half-height, positive right and down), whole pixels at each image's own size. What moves in
    from the border repeats the edge (the surface, or the empty space, beyond the crop goes on as at its edge).
    ``tactile`` and ``prior`` move as their change from ``background`` (which must be in the batch). New
    tensors; other keys are left out."""
    out = {}
    bg = batch.get("background")
    for k in (*SHIFTED_IMAGES, *SENSOR_IMAGES):
        if k not in batch or k == "background":
            continue
        x = batch[k]
        if k in SENSOR_IMAGES:
            if bg is None:
                raise TnfError(f"the shift augmentation moves {k!r} as its change from 'background', not in the batch")
            out[k] = bg + _shift(x - bg, frac)
        else:
            out[k] = _shift(x, frac)
    return out


def _shift(x: torch.Tensor, frac: torch.Tensor) -> torch.Tensor:
    """``x`` [B, C, H, W] moved by ``frac`` [B, 2] of its half-size, rounded to whole pixels, edges repeated."""
    b, _, h, w = x.shape
    f = frac.to(x.device)
    dx = torch.round(f[:, 0] * (w / 2)).long()
    dy = torch.round(f[:, 1] * (h / 2)).long()
    xs = (torch.arange(w, device=x.device)[None, :] - dx[:, None]).clamp_(0, w - 1)  # [B, W]
    ys = (torch.arange(h, device=x.device)[None, :] - dy[:, None]).clamp_(0, h - 1)  # [B, H]
    rows = x.gather(2, ys[:, None, :, None].expand(b, x.shape[1], h, w))
    return rows.gather(3, xs[:, None, None, :].expand(b, x.shape[1], h, w))


def unmirror_channels(mirror: Sequence[int]) -> list[int]:
    """The channel order that undoes ``mirror`` (``x[order][undo] == x``)."""
    undo = [0] * len(mirror)
    for i, c in enumerate(mirror):
        undo[c] = i
    return undo


def augment_batch(
    batch: Batch,
    augment: Sequence[str],
    mirror: Sequence[int] | None = None,
    generator: torch.Generator | None = None,
) -> None:
    """The augmentations named in ``augment`` (see ``AUGMENTATIONS``) on a float batch, each pair drawn on its
    own; the batch's images are replaced by new tensors (a shared, stride-0 background is never written to).
    ``mirror`` is the sensor's channel order under the mirror (``sensor_mirror``); ``generator`` (a CPU
    generator) draws the random choices, torch's global one when None.
    """
    b = batch["rgb"].shape[0]
    if "mirror" in augment:
        if mirror is None:
            raise TnfError("the mirror augmentation needs the sensor's channel order (sensor_mirror)")
        flip = (torch.rand(b, generator=generator) < 0.5).to(batch["rgb"].device).view(b, 1, 1, 1)
        whole = mirror_batch(batch, mirror)
        for k in whole:
            batch[k] = torch.where(flip, whole[k], batch[k])
    if "shift" in augment:
        # Half the pairs stay where the simulator pressed them; the others move anywhere a centred contact can
        # go on the gel (up to its half-width and half-height each way).
        move = (torch.rand(b, generator=generator) < 0.5).to(batch["rgb"].device).view(b, 1, 1, 1)
        frac = 2 * torch.rand(b, 2, generator=generator) - 1
        moved = shift_batch(batch, frac)
        for k in moved:
            batch[k] = torch.where(move, moved[k], batch[k])
    if "jitter" in augment:
        gain = 1 + 0.2 * (torch.rand(b, 1, 1, 1, generator=generator) - 0.5)
        shift = 0.2 * (torch.rand(b, 1, 1, 1, generator=generator) - 0.5)
        rgb = batch["rgb"]
        batch["rgb"] = (rgb * gain.to(rgb.device) + shift.to(rgb.device)).clamp_(-1, 1)
