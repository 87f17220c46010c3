"""The touch record: one entry of a touch item's manifest ``touches`` list, read and written here only.

``tnf touch`` (simulated and imported touches) and ``tnf generate`` write touch items: ``images/*.png`` and a
``manifest.json`` whose ``touches`` list holds one :class:`TouchRecord` per image. ``tnf pair``, the force
datasets, ``tnf generate`` (``touch_force=sim``) and the evaluation read them with :func:`read_touch_records`
or :func:`touch_records_of`.

Poses are [4, 4] camera-to-world matrices in metres, OpenGL convention: the sensor looks along its -z axis.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from tnf.artifacts import MANIFEST, read_json
from tnf.errors import TnfError

Matrix = tuple[tuple[float, ...], ...]  # [4, 4] row-major
Point = tuple[float, ...]  # [3]


def as_matrix(m: Any) -> Matrix:
    """A [4, 4] pose (array or nested lists) as nested tuples of its values (``tolist``'s floats, unchanged)."""
    rows = m.tolist() if hasattr(m, "tolist") else m
    return tuple(tuple(r) for r in rows)


def as_point(p: Any) -> Point:
    """A [3] point (array or list) as a tuple of its values."""
    return tuple(p.tolist() if hasattr(p, "tolist") else p)


@dataclass(frozen=True)
class TouchRecord:
    """One touch of a touch item: its image and where the sensor was.

    Fields written as ``None`` are optional: ``contact_c2w``, ``force_target``, ``force_band`` and ``pose_index``
    are left out of the JSON when None; ``contact_point``, ``force`` and ``penetration`` are written as null.
    """

    index: int  # the touch's number in its item (its image is usually ``images/<index:05d>.png``)
    split: str  # train, val or novel_view
    image: str  # the tactile image, relative to the item's folder
    start_c2w: Matrix  # [4, 4] camera-to-world, metres: the sensor's pose before it advances (the camera pose)
    contact_c2w: Matrix | None = None  # [4, 4] camera-to-world, metres: the sensor's pose while pressing
    contact_point: Point | None = None  # [3] metres, world: where the gel meets the surface (None: no contact)
    force: float | None = None  # newtons: the normal force pressed (None: not measured)
    penetration: float | None = None  # metres: how far the gel went into the surface (None: not measured)
    force_target: float | None = None  # newtons: the force the touch was asked for (touch.force_range)
    force_band: str | None = None  # the target force's band: train, interpolation, extrapolation or outside
    pose_index: int | None = None  # generated touches: the number of the pose the image was made at

    def to_json(self) -> dict[str, Any]:
        """The manifest entry: keys in the order ``tnf touch`` and ``tnf generate`` have always written them."""
        out: dict[str, Any] = {
            "index": self.index,
            "split": self.split,
            "image": self.image,
            "start_c2w": [list(r) for r in self.start_c2w],
        }
        if self.contact_c2w is not None:
            out["contact_c2w"] = [list(r) for r in self.contact_c2w]
        out["contact_point"] = None if self.contact_point is None else list(self.contact_point)
        out["force"] = self.force
        out["penetration"] = self.penetration
        for key in ("force_target", "force_band", "pose_index"):
            if getattr(self, key) is not None:
                out[key] = getattr(self, key)
        return out

    @classmethod
    def from_json(cls, entry: Any, where: str | Path, i: int) -> TouchRecord:
        """Entry ``i`` of the ``touches`` list of the manifest ``where``, validated; a one-line TnfError naming
        the file and the entry when it is malformed. Keys other than the fields are ignored."""

        def bad(what: str) -> TnfError:
            return TnfError(f"touch manifest {where}: touch {i} {what}; rerun `tnf touch`")

        if not isinstance(entry, Mapping):
            raise bad("is not an object")
        for key in ("index", "split", "image", "start_c2w"):
            if key not in entry:
                raise bad(f"lacks {key!r}")
        if not _is_int(entry["index"]):
            raise bad(f"'index' must be an integer, got {entry['index']!r:.40}")
        if not isinstance(entry["image"], str) or not isinstance(entry["split"], str):
            raise bad("'image' and 'split' must be strings")
        start = _matrix(entry["start_c2w"])
        if start is None:
            raise bad("start_c2w must be a finite 4x4 matrix")
        contact_c2w = entry.get("contact_c2w")
        if contact_c2w is not None and (contact_c2w := _matrix(contact_c2w)) is None:
            raise bad("contact_c2w must be a finite 4x4 matrix")
        point = entry.get("contact_point")
        if point is not None and (point := _numbers(point, 3, finite=False)) is None:
            raise bad("contact_point must be 3 numbers (metres)")
        for key in ("force", "penetration", "force_target"):
            if entry.get(key) is not None and not _is_number(entry[key]):
                raise bad(f"{key!r} must be a number or null, got {entry[key]!r:.40}")
        if entry.get("force_band") is not None and not isinstance(entry["force_band"], str):
            raise bad("'force_band' must be a string")
        if entry.get("pose_index") is not None and not _is_int(entry["pose_index"]):
            raise bad("'pose_index' must be an integer")
        return cls(
            index=entry["index"],
            split=entry["split"],
            image=entry["image"],
            start_c2w=start,
            contact_c2w=contact_c2w,
            contact_point=point,
            force=entry.get("force"),
            penetration=entry.get("penetration"),
            force_target=entry.get("force_target"),
            force_band=entry.get("force_band"),
            pose_index=entry.get("pose_index"),
        )


def touch_records_of(manifest: Any, where: str | Path) -> list[TouchRecord]:
    """The touch records of a touch item's parsed ``manifest`` (read from ``where``): its ``touches`` list (or
    ``info.touches``); a one-line TnfError naming ``where`` when there is none or an entry is malformed."""
    touches = None
    if isinstance(manifest, Mapping):
        info = manifest.get("info")
        touches = manifest.get("touches", info.get("touches") if isinstance(info, Mapping) else None)
    if not isinstance(touches, list):
        raise TnfError(f"touch manifest {where} has no 'touches' list; rerun `tnf touch`")
    return [TouchRecord.from_json(t, where, i) for i, t in enumerate(touches)]


def read_touch_records(folder: str | Path) -> list[TouchRecord]:
    """The touch records of the touch item in ``folder`` (its ``manifest.json``)."""
    path = Path(folder) / MANIFEST
    return touch_records_of(read_json(path, "touch manifest"), path)


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _numbers(v: Any, n: int, finite: bool) -> tuple[Any, ...] | None:
    """``v`` as a tuple of ``n`` numbers (finite ones with ``finite``), else None."""
    if not isinstance(v, Sequence) or isinstance(v, str) or len(v) != n:
        return None
    if not all(_is_number(x) and (not finite or math.isfinite(x)) for x in v):
        return None
    return tuple(v)


def _matrix(v: Any) -> Matrix | None:
    """``v`` as a finite 4x4 matrix of nested tuples, else None."""
    if not isinstance(v, Sequence) or isinstance(v, str) or len(v) != 4:
        return None
    rows = [_numbers(r, 4, finite=True) for r in v]
    return None if any(r is None for r in rows) else tuple(r for r in rows if r is not None)
