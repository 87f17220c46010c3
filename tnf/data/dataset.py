"""Reading paired datasets as PyTorch datasets: whole batches are one fancy index into the memory maps."""

from __future__ import annotations

import logging
import os
import warnings
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from torch.utils.data import Dataset, default_collate, get_worker_info

from tnf.data.augment import (
    AUGMENTATIONS,
    MIRRORED_IMAGES,
    SENSOR_IMAGES,
    Batch,
    augment_batch,
    check_augment,
    mirror_augment,
    mirror_batch,
    sensor_mirror,
    unmirror_channels,
)
from tnf.data.splits import SPLITS, split_code
from tnf.data.store import PairArrays, open_pairs
from tnf.errors import TnfError

# The augmentation's names stay importable from here.
__all__ = [
    "AUGMENTATIONS",
    "MIRRORED_IMAGES",
    "SENSOR_IMAGES",
    "Batch",
    "MixedPairDataset",
    "PairBatch",
    "PairDataset",
    "augment_batch",
    "check_augment",
    "check_subsample",
    "collate_pairs",
    "mirror_augment",
    "mirror_batch",
    "sensor_mirror",
    "to_float_batch",
    "training_order",
    "unmirror_channels",
]

log = logging.getLogger(__name__)


class PairBatch(dict):  # type: ignore[type-arg]
    """A batch dict whose images shared by the whole batch (stride-0 expanded backgrounds) stay shared when a
    ``DataLoader(pin_memory=True)`` pins it: ``Tensor.pin_memory`` keeps strides and cannot copy into an
    expanded tensor, so the one shared image is pinned and expanded again."""

    def pin_memory(self) -> PairBatch:
        out = PairBatch()
        for k, v in self.items():
            if v.ndim > 0 and len(v) > 1 and v.stride(0) == 0:
                out[k] = v[:1].pin_memory().expand(v.shape)
            else:
                out[k] = v.pin_memory()
        return out


def _batch_tensor(shape: Sequence[int], dtype: torch.dtype) -> torch.Tensor:
    """An uninitialised CPU tensor for a batch; in a DataLoader worker, in shared memory.

    A worker sends a batch to the main process through shared memory: a tensor allocated there from the start
    goes as a handle, any other is first copied into a new shared segment (a second write of every byte).
    """
    if get_worker_info() is None:
        return torch.empty(tuple(shape), dtype=dtype)
    numel = int(np.prod(shape))
    storage = torch.UntypedStorage._new_shared(numel * dtype.itemsize)
    return torch.empty(0, dtype=dtype).set_(storage).view(tuple(shape))


def _take_rows(array: np.ndarray, rows: np.ndarray) -> torch.Tensor:
    """``array[rows]`` (one copy out of the memory map) as a tensor, in shared memory inside a worker."""
    dtype = torch.from_numpy(np.empty(0, dtype=array.dtype)).dtype
    out = _batch_tensor((len(rows), *array.shape[1:]), dtype)
    # mode="clip": the rows are valid (they come from the dataset's index); the default mode="raise" first
    # gathers into a temporary buffer and copies that (about 2x slower).
    np.take(array, rows, axis=0, out=out.numpy(), mode="clip")
    return out


# x * _U8_SCALE - 1 maps uint8 to [-1, 1] in one fused multiply-add (CPUs and GPUs round it once). The scale is
# the float32 just below 2/255: float32(2/255) itself is a little above 2/255 and maps 255 to 1 + 2**-23, outside
# [-1, 1]; this one maps 0 to -1 exactly, 255 to 1 - 2**-23 and every value within 1.2e-7 of x * 2/255 - 1
# (tests/data/test_dataset.py checks all 256). Depth, float16 in [0, 1], maps by 2d - 1, which is exact.
_U8_SCALE = float(np.nextafter(np.float32(2 / 255), np.float32(0)))
_MINUS_ONE = torch.tensor(-1.0)


# Pairs' float bytes converted per step: in L2-cache-sized steps the cast's output is still in the cache when
# the multiply-add rewrites it, so each float byte goes out to main memory once.
_STEP_BYTES = 1 << 20


def _convert_rows(
    out: torch.Tensor, src: np.ndarray | torch.Tensor, rows: np.ndarray | Sequence[int] | None, scale: float
) -> torch.Tensor:
    """``out[i] = src[rows[i]] * scale - 1`` (``src[i]`` without ``rows``) in float32, and ``out``.

    The rows are first gathered as stored (one ``np.take`` out of the memory map: uint8 or float16, a quarter
    or half of the float bytes), then cast into ``out`` and mapped by the multiply-add in place in steps of
    about ``_STEP_BYTES`` of output, so that the multiply-add finds the cast's output in the L2 cache and each
    float byte goes out to main memory once. Over a whole batch at once the cast and the multiply-add each go
    through main memory (and a single ``torch.add(-1, uint8, alpha=scale)`` on the CPU casts into a temporary
    tensor first); a step per pair, or a step's rows gathered straight from the memory map, costs as much or
    more in per-operation overhead.
    """
    if rows is not None:
        src = np.take(src, rows, axis=0, mode="clip")
    step = max(1, _STEP_BYTES // (out[0].numel() * out.element_size())) if len(out) else 1
    for i in range(0, len(out), step):
        part = out[i : i + step]
        part.copy_(_as_tensor(src[i : i + step]))
        torch.add(_MINUS_ONE, part, alpha=scale, out=part)
    return out


def _to_unit_range(x: np.ndarray | torch.Tensor, rows: np.ndarray | Sequence[int] | None = None) -> torch.Tensor:
    """uint8 [B, H, W, C] -> float32 [B, C, H, W] in [-1, 1], in channels-last memory layout.

    With ``rows``, converts those rows of ``x`` (a uint8 [N, H, W, C] array, e.g. a memory map), in that
    order (``_convert_rows``).

    Converting in place of the stored HWC order avoids a transposing copy (about 2x faster on a CPU);
    convolutions take channels-last tensors as they are, ``.contiguous()`` gives the NCHW layout.
    On a GPU the conversion is one kernel.
    """
    n = len(rows) if rows is not None else len(x)
    shape = (n, *x.shape[1:])
    if isinstance(x, np.ndarray) or x.device.type == "cpu":
        return _convert_rows(_batch_tensor(shape, torch.float32), x, rows, _U8_SCALE).permute(0, 3, 1, 2)
    out = torch.empty(shape, dtype=torch.float32, device=x.device)
    src = x if rows is None else x[torch.as_tensor(rows, device=x.device)]
    return torch.add(_MINUS_ONE, src, alpha=_U8_SCALE, out=out).permute(0, 3, 1, 2)


def _depth_to_unit_range(x: np.ndarray | torch.Tensor, rows: np.ndarray | Sequence[int] | None = None) -> torch.Tensor:
    """float16 depth [B, H, W] in [0, 1] (or the rows ``rows`` of an [N, H, W] array) -> float32 [B, 1, H, W],
    2d - 1 (exact)."""
    n = len(rows) if rows is not None else len(x)
    shape = (n, 1, *x.shape[1:])
    if isinstance(x, np.ndarray) or x.device.type == "cpu":
        out = _batch_tensor(shape, torch.float32)
        _convert_rows(out[:, 0], x, rows, 2.0)
        return out
    out = torch.empty(shape, dtype=torch.float32, device=x.device)
    src = x if rows is None else x[torch.as_tensor(rows, device=x.device)]
    torch.add(_MINUS_ONE, src, alpha=2.0, out=out[:, 0])
    return out


def _as_tensor(x: np.ndarray | torch.Tensor) -> torch.Tensor:
    """A tensor sharing ``x``'s memory; read-only arrays (memory maps opened with mode "r") too: nothing writes
    into them (torch would warn once that it could)."""
    if isinstance(x, torch.Tensor):
        return x
    if x.flags.writeable:
        return torch.from_numpy(x)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="The given NumPy array is not writable")
        return torch.from_numpy(x)


def _gather_backgrounds(backgrounds: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """``backgrounds[index]`` for a batch: when the batch has one background (one sensor), a stride-0
    expanded view of it instead of a copy per pair. Nothing writes into batches in place (``augment_batch``
    replaces a batch's images by new tensors)."""
    if len(backgrounds) == 1:  # a dataset of one sensor: no need to look at the index
        return backgrounds.expand(len(index), *backgrounds.shape[1:])
    first = index[:1]
    if len(index) > 1 and bool((index == first).all()):
        return backgrounds[first].expand(len(index), *backgrounds.shape[1:])
    return backgrounds[index]


class PairDataset(Dataset):
    """Pairs of one dataset folder, restricted to some splits.

    Items (``ds[i]``) and batches (``ds.__getitems__(indices)``, which ``DataLoader`` calls with a whole
    batch of indices) are dicts of float32 tensors in [-1, 1]: ``rgb`` [3, 128, 128], ``depth``
    [1, 128, 128] (-1 nearest, 1 far or empty), ``background`` [3, 128, 128], ``tactile`` [3, 128, 128];
    plus ``object_id`` (long; index into ``object_names``), ``prior`` [3, 128, 128] in datasets that hold
    it (``pair.prior=true``), ``points`` [3, 128, 128] (metres, NaN where no surface) in those that hold
    them (``pair.points=true``) and ``force`` (float32, newtons) in those made with ``pair.force=true``.
    Batches have a leading batch dimension; when all
    pairs of a batch share one background (one sensor), ``background`` is a stride-0 expanded view of it:
    read it freely, but call ``.contiguous()`` before writing into it in place.

    Args:
        folder: a dataset folder (``<root>/pairs/<name>``).
        splits: split names to include (see ``tnf.data.SPLITS``).
        per_object: keep at most this many touches per object (all frames of a chosen touch), drawn with
            ``seed``; None keeps all.
        extra_touches: with ``per_object``, this many more touches drawn at random (``seed``) from all that
            ``per_object`` left out, whatever their object: the paper's T-N+ (5 per object and 45 more). The
            ``per_object`` touches are the same with or without them.
        seed: seed of the per-object subsample.
        object_names: the object vocabulary ``object_id`` indexes; default this dataset's own object list.
            Datasets that are mixed share one vocabulary so an object keeps its id.
        augment: augmentations of each batch, from ``AUGMENTATIONS``: ``mirror`` (the sensor's mirror
            symmetry, which the dataset's manifest records; left out, with a warning, for a sensor without one),
            ``shift`` (the contact moved across the gel) and ``jitter`` (RGB brightness and contrast).
        compact: serve batches as stored (``rgb``, ``background``, ``tactile`` uint8 [B, 128, 128, 3],
            ``depth`` float16 [B, 128, 128]; ``points`` as in float batches), 4x fewer bytes to load, pin and
            copy; ``to_float_batch``
            turns them into the float form, best on the GPU after the copy. ``augment`` is then not applied
            here (apply ``augment_batch`` after ``to_float_batch``).
    """

    def __init__(
        self,
        folder: str | os.PathLike[str],
        splits: Sequence[str] = ("train",),
        per_object: int | None = None,
        seed: int = 0,
        object_names: Sequence[str] | None = None,
        augment: Sequence[str] = (),
        compact: bool = False,
        extra_touches: int = 0,
    ):
        if isinstance(splits, str):
            splits = (splits,)
        check_subsample(per_object, extra_touches)
        self.arrays: PairArrays = open_pairs(folder)
        # Compact batches are augmented after the copy, by PairDataModule (which reads the sensor's mirror itself).
        self.augment, self.mirror = mirror_augment(
            () if compact else check_augment(augment), [(self.arrays.manifest, folder)]
        )
        self.splits = tuple(splits)
        self.compact = compact
        own = self.arrays.objects
        self.object_names = list(object_names) if object_names is not None else own
        missing = [n for n in own if n not in self.object_names]
        if missing:
            raise TnfError(f"object {missing[0]!r} of dataset {folder} is not in the given object_names")
        self._id_map = torch.tensor([self.object_names.index(n) for n in own], dtype=torch.long)

        split = np.asarray(self.arrays.split)
        codes = [split_code(s) for s in self.splits]
        rows = np.flatnonzero(np.isin(split, codes))
        if per_object is not None:
            rows = _subsample_touches(
                rows,
                np.asarray(self.arrays.object_id),
                np.asarray(self.arrays.touch_index),
                per_object,
                seed,
                extra_touches,
            )
        self.index = rows.astype(np.int64)
        # Backgrounds are few (one per sensor): convert once; a batch gets a view of them, not copies.
        self._backgrounds_u8 = torch.from_numpy(np.array(self.arrays.backgrounds))  # [K, H, W, 3]
        self._backgrounds = _to_unit_range(self._backgrounds_u8)  # [K, 3, H, W] float32
        self._bg_index = torch.from_numpy(np.asarray(self.arrays.background_index).astype(np.int64))
        self._object_id = torch.from_numpy(np.asarray(self.arrays.object_id).astype(np.int64))

    def __len__(self) -> int:
        return len(self.index)

    @property
    def manifest(self) -> dict[str, Any]:
        return self.arrays.manifest

    def __getitem__(self, i: int) -> Batch:
        if not -len(self) <= i < len(self):
            raise IndexError(f"index {i} out of range for {len(self)} pairs")
        return {k: v[0] for k, v in self.__getitems__([i]).items()}

    def __getitems__(self, indices: Sequence[int]) -> Batch:
        """A batch of pairs as one dict of stacked tensors."""
        rows = self.index[np.asarray(indices, dtype=np.int64)]
        a = self.arrays
        rows_t = torch.from_numpy(rows)
        # (Advanced indexing, not index_select: the latter is far slower for large rows on the CPU.)
        object_id = self._id_map[self._object_id[rows_t]]
        bg_index = self._bg_index[rows_t]
        if self.compact:
            out = PairBatch(
                {
                    "rgb": _take_rows(a.rgb, rows),
                    "depth": _take_rows(a.depth, rows),
                    "background": _gather_backgrounds(self._backgrounds_u8, bg_index),
                    "tactile": _take_rows(a.tactile, rows),
                    "object_id": object_id,
                }
            )
            if a.prior is not None:
                out["prior"] = _take_rows(a.prior, rows)
            if a.points is not None:  # float32 either way: served as the float batches serve them
                out["points"] = _points_chw(_take_rows(a.points, rows))
            if a.force is not None:
                out["force"] = _take_rows(a.force, rows)
            return out
        # Rows gathered out of the page cache (the memory maps) as stored, then converted in cache-sized steps.
        rgb = _to_unit_range(a.rgb, rows)
        tactile = _to_unit_range(a.tactile, rows)
        depth = _depth_to_unit_range(a.depth, rows)
        background = _gather_backgrounds(self._backgrounds, bg_index)
        batch = PairBatch(rgb=rgb, depth=depth, background=background, tactile=tactile, object_id=object_id)
        if a.prior is not None:
            batch["prior"] = _to_unit_range(a.prior, rows)
        if a.points is not None:
            batch["points"] = _points_chw(_take_rows(a.points, rows))
        if a.force is not None:
            batch["force"] = _take_rows(a.force, rows)
        if self.augment:
            augment_batch(batch, self.augment, self.mirror)
        return batch

    def split_counts(self) -> dict[str, int]:
        """Number of pairs per split in this (possibly subsampled) dataset."""
        codes = np.asarray(self.arrays.split)[self.index]
        return {s: int((codes == i).sum()) for i, s in enumerate(SPLITS) if s in self.splits}


def to_float_batch(batch: Batch) -> Batch:
    """A compact batch (uint8 HWC images, float16 depth) as float32 [B, C, H, W] tensors in [-1, 1] (images
    channels-last in memory), on the batch's device.

    Float batches pass through unchanged, so it is safe to call on any batch.
    """
    out = dict(batch)
    for k in ("rgb", "background", "tactile", "prior"):
        if k not in batch:
            continue
        x = batch[k]
        if x.dtype == torch.uint8:
            if x.ndim == 4 and len(x) > 1 and x.stride(0) == 0:  # one background expanded: convert it once
                out[k] = _to_unit_range(x[:1]).expand(len(x), -1, -1, -1)
            else:
                out[k] = _to_unit_range(x)
    d = batch["depth"]
    if d.ndim == 3:
        out["depth"] = _depth_to_unit_range(d)
    return out


def _points_chw(points: torch.Tensor) -> torch.Tensor:
    """Surface points [B, H, W, 3] as stored -> [B, 3, H, W] float32 (channels-last in memory, as the images)."""
    return points.float().permute(0, 3, 1, 2)


def training_order(trained: Sequence[str] | None, own: Sequence[str]) -> list[str] | None:
    """Object names for ``PairDataset(object_names=...)`` so that ids match a model's training data: the objects it
    was trained on (its manifest's ``object_names``) in that order, then the dataset's others. None (the dataset's
    own order) for a model that records none. A surface field (``tnf.generators.field``) knows objects by these ids."""
    if not trained:
        return None
    return list(trained) + [o for o in own if o not in trained]


def check_subsample(per_object: Any, extra_touches: Any) -> None:
    """A TnfError unless ``per_object`` is None or a whole number >= 1 and ``extra_touches`` a whole number >= 0
    that only comes with ``per_object`` (it adds to per_object's touches)."""

    def whole(x: Any) -> bool:
        return isinstance(x, (int, np.integer)) and not isinstance(x, bool)

    if per_object is not None and not (whole(per_object) and per_object >= 1):
        raise TnfError(f"data.per_object must be a whole number >= 1 or null, got {per_object!r}")
    if not (whole(extra_touches) and extra_touches >= 0):
        raise TnfError(f"data.extra_touches must be a whole number >= 0, got {extra_touches!r}")
    if extra_touches and per_object is None:
        raise TnfError(
            f"data.extra_touches={extra_touches} adds to data.per_object's touches: give data.per_object too"
        )


def _subsample_touches(
    rows: np.ndarray, object_id: np.ndarray, touch_index: np.ndarray, per_object: int, seed: int, extra: int = 0
) -> np.ndarray:
    """Keep the rows of at most ``per_object`` touches per object (chosen at random with ``seed``), then of
    ``extra`` more touches drawn from all the others (fewer where fewer are left); ``check_subsample`` checked
    both."""
    rng = np.random.default_rng(seed)
    keep = np.zeros(len(rows), dtype=bool)
    obj = object_id[rows]
    touch = touch_index[rows]
    for o in np.unique(obj):
        in_obj = obj == o
        touches = np.unique(touch[in_obj])
        if len(touches) > per_object:
            touches = np.sort(rng.choice(touches, size=per_object, replace=False))
        keep |= in_obj & np.isin(touch, touches)
    if extra:  # drawn after every object's own, so that those are the same with or without the extra ones
        left = np.unique(np.stack([obj[~keep], touch[~keep]], axis=1), axis=0)  # (object, touch) pairs
        chosen = left[rng.choice(len(left), size=min(extra, len(left)), replace=False)]
        for o, t in chosen:
            keep |= (obj == o) & (touch == t)
    return rows[keep]


class MixedPairDataset(Dataset):
    """Several ``PairDataset``s served as one (e.g. simulated and generated touches); batches as above, with
    ``prior``, ``points`` and ``force`` only when every dataset holds them."""

    def __init__(self, datasets: Sequence[PairDataset]):
        if not datasets:
            raise TnfError("no datasets to mix")
        self.datasets = list(datasets)
        self.offsets = np.cumsum([0] + [len(d) for d in self.datasets])
        self._drop = tuple(
            k for k in ("prior", "points", "force") if not all(getattr(d.arrays, k) is not None for d in self.datasets)
        )

    def __len__(self) -> int:
        return int(self.offsets[-1])

    def __getitem__(self, i: int) -> Batch:
        return {k: v[0] for k, v in self.__getitems__([i]).items()}

    def __getitems__(self, indices: Sequence[int]) -> Batch:
        idx = np.asarray(indices, dtype=np.int64)
        which = np.searchsorted(self.offsets, idx, side="right") - 1
        parts = [(np.flatnonzero(which == d), idx[which == d] - self.offsets[d]) for d in np.unique(which)]
        if len(parts) == 1:
            one = self.datasets[int(which[0])].__getitems__(parts[0][1])
            for k in self._drop:
                one.pop(k, None)
            return one
        fetched = [self.datasets[int(which[pos[0]])].__getitems__(local) for pos, local in parts]
        out: Batch = {}
        for k, v in fetched[0].items():
            if k in self._drop:
                continue
            # Same memory layout as the parts (channels-last float images), so the copies below do not transpose.
            fmt = torch.channels_last if v.ndim == 4 and v.is_contiguous(memory_format=torch.channels_last) else None
            out[k] = torch.empty((len(idx), *v.shape[1:]), dtype=v.dtype, memory_format=fmt or torch.contiguous_format)
            for (pos, _), f in zip(parts, fetched):
                out[k][torch.from_numpy(pos)] = f[k]
        return out


def collate_pairs(batch: Any) -> Batch:
    """DataLoader collate function: batches from ``__getitems__`` are already stacked."""
    if isinstance(batch, dict):
        return batch
    return default_collate(batch)
