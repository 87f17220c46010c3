"""The on-disk format of a paired dataset: a folder of memory-mappable ``.npy`` arrays and a manifest.

``<root>/pairs/<name>/``:

- ``rgb.npy`` uint8 [N, 128, 128, 3]: rendered colour, centre-cropped;
- ``depth.npy`` float16 [N, 128, 128]: normalised depth in [0, 1] (1 = no surface);
- ``tactile.npy`` uint8 [N, 128, 128, 3]: the tactile image;
- ``backgrounds.npy`` uint8 [K, 128, 128, 3] and ``background_index.npy`` int32 [N]: the sensor's
  no-contact image of each pair, stored once per distinct background;
- ``object_id.npy`` int32 [N] (index into the manifest's ``objects``), ``split.npy`` int8 [N] (index into
  ``splits``), ``touch_index.npy`` int32 [N] (the touch's index in its touch manifest), ``sensor_id.npy``
  int16 [N] (index into ``sensors``);
- ``prior.npy`` uint8 [N, 128, 128, 3], only in datasets made with ``pair.prior=true`` (the manifest's
  ``prior`` says how): the simulator's image of the pair's depth crop (``tnf.data.prior``);
- ``points.npy`` float32 [N, 128, 128, 3], only in datasets made with ``pair.points=true`` (the manifest's
  ``points``): the surface point each RGB-D pixel sees, in the object's frame (metres; NaN where none);
- ``force.npy`` float32 [N], only in datasets made with ``pair.force=true`` (the manifest's ``force``): the
  normal force of each pair's touch, newtons (``tnf.sim.forces``);
- ``manifest.json``: provenance and counts; ``previews/``: a few pairs as PNG.

Arrays are written in place through ``np.lib.format.open_memmap`` so a dataset of any size is built with
bounded memory, and read back with ``mmap_mode="r"`` so loading holds only the pages it touches.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from tnf.artifacts import CACHE_VERSION, MANIFEST, read_json, write_json
from tnf.data.preprocess import SIZE
from tnf.data.splits import SPLITS
from tnf.errors import TnfError

FORMAT_VERSION = CACHE_VERSION
"""The version a dataset's manifest records (``format_version``); a dataset of another one is refused."""

# name -> (dtype, shape after N)
PAIR_ARRAYS: dict[str, tuple[str, tuple[int, ...]]] = {
    "rgb": ("uint8", (SIZE, SIZE, 3)),
    "depth": ("float16", (SIZE, SIZE)),
    "tactile": ("uint8", (SIZE, SIZE, 3)),
    "background_index": ("int32", ()),
    "object_id": ("int32", ()),
    "split": ("int8", ()),
    "touch_index": ("int32", ()),
    "sensor_id": ("int16", ()),
}
OPTIONAL_ARRAYS: dict[str, tuple[str, tuple[int, ...]]] = {
    "prior": ("uint8", (SIZE, SIZE, 3)),
    "points": ("float32", (SIZE, SIZE, 3)),
    "force": ("float32", ()),
}
"""Arrays a dataset holds only when its manifest names them (``prior``: ``pair.prior=true``; ``points``:
``pair.points=true``; ``force``: ``pair.force=true``)."""


class PairWriter:
    """Fills the arrays of a dataset of ``n`` pairs chunk by chunk, straight into memory-mapped files.

    ``with PairWriter(folder, n, backgrounds) as w: w.write(start, rgb=..., depth=..., ...)``; then write the
    manifest with ``write_manifest``. Memory use is that of the chunks passed in. ``optional`` names the arrays
    of ``OPTIONAL_ARRAYS`` this dataset has (each ``write`` must then give them too).
    """

    def __init__(self, folder: str | os.PathLike[str], n: int, backgrounds: np.ndarray, optional: tuple[str, ...] = ()):
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.n = int(n)
        bg = np.asarray(backgrounds)
        if bg.ndim != 4 or bg.shape[1:] != (SIZE, SIZE, 3) or bg.dtype != np.uint8:
            raise ValueError(f"backgrounds must be uint8 [K, {SIZE}, {SIZE}, 3], got {bg.dtype} {bg.shape}")
        np.save(self.folder / "backgrounds.npy", bg)
        unknown = [k for k in optional if k not in OPTIONAL_ARRAYS]
        if unknown:
            raise ValueError(f"unknown optional arrays {unknown}; known: {sorted(OPTIONAL_ARRAYS)}")
        self.layout = {**PAIR_ARRAYS, **{k: OPTIONAL_ARRAYS[k] for k in optional}}
        self.arrays = {
            name: np.lib.format.open_memmap(
                self.folder / f"{name}.npy", mode="w+", dtype=np.dtype(dt), shape=(self.n, *shape)
            )
            for name, (dt, shape) in self.layout.items()
        }
        self.written = np.zeros(self.n, dtype=bool)

    def write(self, start: int, **chunk: np.ndarray) -> None:
        """Write rows ``start : start + len`` of every array (all arrays of the layout must be given)."""
        missing, extra = set(self.layout) - set(chunk), set(chunk) - set(self.layout)
        if missing or extra:
            raise ValueError(f"missing arrays: {sorted(missing)}; unexpected: {sorted(extra)}")
        k = len(chunk["rgb"])
        for name, arr in chunk.items():
            self.arrays[name][start : start + k] = arr
        self.written[start : start + k] = True

    def close(self) -> None:
        if not self.written.all():
            raise RuntimeError(f"{int((~self.written).sum())} of {self.n} pairs were never written")
        for arr in self.arrays.values():
            arr.flush()
        self.arrays.clear()

    def __enter__(self) -> PairWriter:
        return self

    def __exit__(self, exc_type: Any, *rest: Any) -> None:
        if exc_type is None:
            self.close()
        else:
            self.arrays.clear()


def dataset_name(pair: Any, sensor: str, scene: str) -> str:
    """``pair.name``, or ``<sensor>-<scene>`` (fitted scenes) / ``<sensor>-mesh`` (ground-truth mesh).

    ``pair`` is the ``pair`` section (``PairSettings``, or its config node); ``sensor`` and ``scene`` are the
    sensor's and the scene kind's names."""
    if pair.name:
        return str(pair.name)
    return f"{sensor}-{scene if pair.scene_source == 'fitted' else 'mesh'}"


def write_manifest(folder: str | os.PathLike[str], info: Mapping[str, Any]) -> None:
    """Write ``manifest.json`` with the format version and split names added."""
    write_json(Path(folder) / MANIFEST, {"format_version": FORMAT_VERSION, "splits": list(SPLITS), **info})


@dataclass
class PairArrays:
    """A dataset folder opened read-only: memory-mapped arrays plus the manifest."""

    folder: Path
    manifest: dict[str, Any]
    rgb: np.ndarray
    depth: np.ndarray
    tactile: np.ndarray
    backgrounds: np.ndarray
    background_index: np.ndarray
    object_id: np.ndarray
    split: np.ndarray
    touch_index: np.ndarray
    sensor_id: np.ndarray
    prior: np.ndarray | None = None
    points: np.ndarray | None = None
    force: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.rgb)

    @property
    def objects(self) -> list[str]:
        return list(self.manifest["objects"])


def check_format(manifest: Any, folder: str | os.PathLike[str]) -> None:
    """Refuse the ``manifest`` of the dataset in ``folder`` unless it is a JSON object of this ``FORMAT_VERSION``
    (a TnfError that says to rebuild it)."""
    if not isinstance(manifest, dict):
        raise TnfError(f"dataset manifest {Path(folder) / MANIFEST} is not a JSON object; {_rebuild(folder)}")
    if manifest.get("format_version") != FORMAT_VERSION:
        raise TnfError(
            f"dataset {folder} has format version {manifest.get('format_version')!r}, this tnf reads "
            f"{FORMAT_VERSION}; {_rebuild(folder)}"
        )


def _rebuild(folder: str | os.PathLike[str]) -> str:
    """How to rebuild dataset ``folder``: `tnf pair` keeps a dataset whose manifest matches its settings, so a
    damaged one in the store is removed first."""
    f = Path(folder)
    if f.parent.name == "pairs":
        return f"rebuild it: `tnf clean pair {f.name}`, then `tnf pair` with its settings"
    return "rebuild it with `tnf pair`"


def open_pairs(folder: str | os.PathLike[str]) -> PairArrays:
    """Open a dataset folder (``<root>/pairs/<name>``) memory-mapped; TnfError when it is not one."""
    folder = Path(folder)
    if not (folder / MANIFEST).is_file():
        raise TnfError(f"not a paired dataset (no {MANIFEST}): {folder}; build one with `tnf pair`")
    manifest = read_json(folder / MANIFEST, "dataset manifest")
    check_format(manifest, folder)
    objects = manifest.get("objects")
    if not isinstance(objects, list) or not objects or not all(isinstance(o, str) for o in objects):
        raise TnfError(f"dataset {folder}: the manifest's 'objects' must be a non-empty list of object names")
    arrays: dict[str, np.ndarray] = {}
    expected = {**PAIR_ARRAYS, "backgrounds": ("uint8", (SIZE, SIZE, 3))}
    expected.update({k: v for k, v in OPTIONAL_ARRAYS.items() if manifest.get(k)})
    for name, (dtype, shape) in expected.items():
        path = folder / f"{name}.npy"
        try:
            arrays[name] = np.load(path, mmap_mode="r")
        except FileNotFoundError:
            raise TnfError(f"dataset {folder} is incomplete: {path.name} is missing; {_rebuild(folder)}") from None
        except (OSError, ValueError, EOFError) as e:  # not a .npy file, truncated, pickled objects
            raise TnfError(f"dataset {folder}: {path.name} is not a readable array ({e}); {_rebuild(folder)}") from None
        a = arrays[name]
        if a.dtype != np.dtype(dtype) or a.ndim != 1 + len(shape) or a.shape[1:] != shape:
            raise TnfError(
                f"dataset {folder}: {path.name} is {a.dtype} {list(a.shape)}, expected {dtype} [N, "
                f"{', '.join(map(str, shape))}]".replace(", ]", "]")
                + f"; {_rebuild(folder)}"
            )
    n = len(arrays["rgb"])
    for name in (k for k in expected if k != "backgrounds"):
        if len(arrays[name]) != n:
            raise TnfError(f"dataset {folder} is inconsistent: {name}.npy has {len(arrays[name])} rows, rgb.npy {n}")
    count = manifest.get("count")
    if count is not None and count != n:
        raise TnfError(f"dataset {folder}: the manifest says {count} pairs but the arrays hold {n}; {_rebuild(folder)}")
    # Index arrays must point into what they index (a bad index would fail deep inside a data loader).
    limits = {
        "object_id": (len(objects), "the manifest's objects"),
        "split": (len(SPLITS), "the splits"),
        "background_index": (len(arrays["backgrounds"]), "backgrounds.npy"),
    }
    for name, (k, what) in limits.items():
        a = np.asarray(arrays[name])
        if n and (a.min() < 0 or a.max() >= k):
            raise TnfError(
                f"dataset {folder}: {name}.npy holds values in [{a.min()}, {a.max()}] but {what} has {k} "
                f"entries; the manifest does not match the arrays, {_rebuild(folder)}"
            )
    return PairArrays(folder=folder, manifest=manifest, **arrays)
