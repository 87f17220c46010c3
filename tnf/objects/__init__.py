"""Object sources: where the rigid objects that tnf captures and touches come from.

An object source (registry ``OBJECTS``) lists object names and loads each as a ``trimesh.Trimesh`` in metres,
centred at the origin (bounding-box centre), z up, with visual colours (vertex colours or a texture), and
validated (:func:`validate_mesh`). In-tree sources: ``builtin`` (procedural household objects, the default),
``mesh_dir`` (a folder of mesh files, YCB layout included), ``pybullet`` (the objects of ``pybullet_data``) and
``captured`` (a user's own camera images and tactile frames, no meshes: :meth:`ObjectSource.views` and
:meth:`ObjectSource.touches` give their files, which ``tnf capture`` and ``tnf touch`` import).

    src = OBJECTS.build(cfg.objects)          # or: src, names = select(cfg.objects, names)
    mesh = src.load("mug")                   # trimesh.Trimesh, metres
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from tnf.errors import TnfError
from tnf.registry import OBJECTS, split_spec

if TYPE_CHECKING:  # pragma: no cover
    import trimesh

log = logging.getLogger(__name__)

# A mesh thinner than this along any axis (metres after scaling) is flat, not a solid object.
MIN_EXTENT = 1e-4
# Largest extent (metres after scaling) of an object a fingertip sensor touches on a table: about 1 cm to 1 m.
# Outside REFUSE_SIZE the mesh is refused (a unit mix-up: millimetres read as metres, or a scale applied twice);
# outside WARN_SIZE a warning is logged.
REFUSE_SIZE = (1e-3, 10.0)
WARN_SIZE = (5e-3, 1.5)

# Why each object checked by ObjectSource.usable failed (None: valid), by source, file, settings and file time.
_ERRORS: dict[tuple[Any, ...], str | None] = {}

TOUCH_SPLITS = ("train", "val", "novel_view")
"""The split labels a touch may carry (a captured object's ``touches.json``, the touch stage's manifest)."""


class ObjectSource:
    """Base class of object sources. Subclasses implement ``names`` and ``_load``.

    ``load`` adds centring and validation on top of ``_load`` so that every source returns meshes that
    follow the same contract.
    """

    #: registry name of the source, set by subclasses (used as the artifact item key)
    name: str = "objects"
    #: when true, callers that go through many objects skip ones that fail to load, logging why
    skip_invalid: bool = False

    def names(self) -> list[str]:
        """The object names this source provides, sorted."""
        raise NotImplementedError

    def _load(self, name: str) -> trimesh.Trimesh:
        """Load object ``name`` as a mesh in metres (not necessarily centred)."""
        raise NotImplementedError

    def where(self, name: str) -> str:
        """Where object ``name`` comes from (a file path or a description), for error messages."""
        return f"{self.name} object {name!r}"

    def load(self, name: str) -> trimesh.Trimesh:
        """Object ``name`` as a ``trimesh.Trimesh``: metres, centred at the origin, validated, with colours.

        A largest extent outside ``REFUSE_SIZE`` (1 mm .. 10 m) is a TnfError, outside ``WARN_SIZE`` (5 mm .. 1.5 m)
        a logged warning, both naming the object, its size and ``objects.scale`` (a unit mix-up, most likely).
        """
        import trimesh

        self.check_name(name)
        mesh = self._load(name)
        if not isinstance(mesh, trimesh.Trimesh):
            raise TnfError(
                f"{self.where(name)}: source {self.name!r} loaded a {type(mesh).__module__}.{type(mesh).__name__}, "
                "not a trimesh.Trimesh; _load must return one mesh (a trimesh.Scene: scene.to_geometry(); "
                "a file: tnf.objects.mesh_dir.load_mesh_file)"
            )
        mesh = centre(mesh)
        # Size first: a mesh in metres read with objects.scale=0.001 is also "flat", which would hide the cause.
        size = _largest_extent(mesh)
        if size is not None and not REFUSE_SIZE[0] <= size <= REFUSE_SIZE[1]:
            raise TnfError(self.size_message(name, size, refused=True))
        validate_mesh(mesh, self.where(name))
        if size is not None and not WARN_SIZE[0] <= size <= WARN_SIZE[1]:
            log.warning("%s", self.size_message(name, size, refused=False))
        return mesh

    def size_message(self, name: str, size: float, refused: bool) -> str:
        """One line on object ``name`` being ``size`` metres across: implausible (``refused``) or unusual, naming
        ``objects.scale`` (its value, where the source has one) and the likely fix."""
        scale = getattr(getattr(self, "cfg", None), "scale", None)
        has_scale = isinstance(scale, (int, float)) and not isinstance(scale, bool)
        lo, hi = REFUSE_SIZE if refused else WARN_SIZE
        head = (
            f"{self.where(name)}: object {name!r} is {size:.3g} m across (largest extent)"
            + (f" with objects.scale={scale:g}" if has_scale else "")
            + (", implausible" if refused else ", unusual")
            + f" for a tabletop object ({_metres(lo)} .. {_metres(hi)}{' allowed' if refused else ' expected'})"
        )
        if not has_scale:
            return f"{head}; source {self.name!r} has no objects.scale setting: its meshes must be in metres"
        scale = float(scale)  # type: ignore[arg-type]
        # The power of 1000 (mm <-> m <-> km) that brings the object nearest to 10 cm across.
        factor = 1000.0 ** min(max(round((math.log10(0.1) - math.log10(size)) / 3), -50), 50)
        if size > hi:
            fix = " (a mesh in millimetres needs objects.scale=0.001)" if scale == 1 else ""
        else:
            fix = " (a mesh in metres needs objects.scale=1)" if scale != 1 and scale * factor != 1 else ""
        if factor == 1 or (size < lo and scale == 1):  # no unit nearer to 10 cm, or tiny in the file's own units
            return f"{head}; check objects.scale if the mesh is not in metres{fix}"
        return f"{head}; a unit mix-up? objects.scale={scale * factor:g} makes it {size * factor:.3g} m{fix}"

    def load_or_skip(self, name: str) -> trimesh.Trimesh | None:
        """Like ``load``, but returns None (and logs why) for an invalid mesh when ``skip_invalid`` is set."""
        try:
            return self.load(name)
        except TnfError as e:
            if not self.skip_invalid:
                raise
            log.warning("skipping invalid object %s: %s", name, e)
            return None

    def usable(self, names: Sequence[str]) -> list[str]:
        """``names`` less the objects whose mesh fails to load or validate, each logged with why, when
        ``skip_invalid`` is set (else all of ``names``), so that every stage of a run leaves out the same ones.
        A TnfError when none is left."""
        if not self.skip_invalid:
            return list(names)
        errors = {n: self._error(n) for n in names if self.views(n) is None}
        kept = [n for n in names if errors.get(n) is None]
        if names and not kept:
            bad = [e for e in errors.values() if e is not None]
            more = f" (and {len(bad) - 1} more invalid objects)" if len(bad) > 1 else ""
            raise TnfError(f"no valid object: {bad[0]}{more}")
        return kept

    def _error(self, name: str) -> str | None:
        """Why object ``name`` fails to load or validate, or None; logged once, and remembered while its file is
        unchanged."""
        where = Path(self.where(name))
        stat = where.stat() if where.is_file() else None
        key = (type(self).__qualname__, str(where), repr(getattr(self, "cfg", None)), stat and stat.st_mtime_ns)
        if key not in _ERRORS:
            try:
                self.load(name)
                _ERRORS[key] = None
            except TnfError as e:
                _ERRORS[key] = str(e)
                log.warning("skipping invalid object %s: %s", name, e)
        return _ERRORS[key]

    def check_name(self, name: str) -> None:
        names = self.names()
        if name not in names:
            raise TnfError(f"unknown object {name!r} in source {self.name!r}; available: {_short_list(names)}")

    def views(self, name: str) -> Path | None:
        """The object's own camera images: its ``transforms.json`` (instant-ngp / nerfstudio format), or None
        when the source has meshes. ``tnf capture`` imports such views instead of rendering the mesh."""
        return None

    def touches(self, name: str) -> Path | None:
        """The object's real tactile frames: its ``touches.json`` (layout in :mod:`tnf.objects.captured`), or
        None when ``tnf touch`` simulates them from the mesh."""
        return None

    def info(self, name: str) -> dict[str, Any]:
        """Size and complexity of object ``name``: ``{"size_m": [dx, dy, dz], "triangles": n, "vertices": n}``."""
        mesh = self.load(name)
        return mesh_info(mesh)


def mesh_info(mesh: trimesh.Trimesh) -> dict[str, Any]:
    """``{"size_m": [dx, dy, dz] metres, "triangles": n, "vertices": n, "watertight": bool}`` of a mesh."""
    return {
        "size_m": [float(x) for x in mesh.extents],
        "triangles": int(len(mesh.faces)),
        "vertices": int(len(mesh.vertices)),
        "watertight": bool(mesh.is_watertight),
    }


def _largest_extent(mesh: Any) -> float | None:
    """The largest bounding-box side (metres) of a mesh with faces and finite vertices, else None (validation
    says what is wrong)."""
    try:
        v = np.asarray(mesh.vertices, dtype=np.float64)
        if not len(mesh.faces):
            return None
    except (AttributeError, TypeError, ValueError):
        return None
    if v.ndim != 2 or v.shape[1] != 3 or not len(v) or not np.isfinite(v).all():
        return None
    size = float((v.max(0) - v.min(0)).max())
    return size if 0 < size < math.inf else None  # a point or an overflow: validation says what is wrong


def _metres(x: float) -> str:
    return f"{x * 1000:g} mm" if x < 0.01 else f"{x:g} m"


def centre(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """Translate ``mesh`` (in place, also returned) so that its bounding-box centre is the origin."""
    if len(mesh.vertices) and np.isfinite(mesh.vertices).all():
        lo, hi = mesh.vertices.min(0), mesh.vertices.max(0)
        mesh.apply_translation(-(lo + hi) / 2)
    return mesh


def validate_mesh(mesh: Any, where: str) -> None:
    """Raise a TnfError naming ``where`` (a file or object) if ``mesh`` is not a usable solid object.

    Checks: a ``trimesh.Trimesh`` with vertices and faces, all vertices finite, face indices in range, a
    positive surface area, an extent of at least 0.1 mm along every axis (not flat or a line), and, when the
    mesh is closed, a non-zero volume.
    """
    import trimesh

    if not isinstance(mesh, trimesh.Trimesh):
        raise TnfError(f"{where}: expected a triangle mesh, got {type(mesh).__name__}")
    if len(mesh.vertices) == 0 or len(mesh.faces) == 0:
        raise TnfError(f"{where}: empty mesh ({len(mesh.vertices)} vertices, {len(mesh.faces)} faces)")
    v = np.asarray(mesh.vertices)
    if not np.isfinite(v).all():
        bad = int((~np.isfinite(v).all(axis=1)).sum())
        raise TnfError(f"{where}: {bad} vertices are NaN or infinite")
    f = np.asarray(mesh.faces)
    if f.min() < 0 or f.max() >= len(v):
        raise TnfError(f"{where}: face indices out of range 0..{len(v) - 1}")
    area = float(mesh.area)
    if not np.isfinite(area) or area <= 0:
        raise TnfError(f"{where}: degenerate mesh (surface area {area:g} m^2)")
    ext = v.max(0) - v.min(0)
    if ext.min() < MIN_EXTENT:
        raise TnfError(
            f"{where}: degenerate mesh, extent {ext[0]:.3g} x {ext[1]:.3g} x {ext[2]:.3g} m "
            f"is flat (needs >= {MIN_EXTENT:g} m along every axis)"
        )
    if mesh.is_watertight:
        vol = abs(float(mesh.volume))
        if not np.isfinite(vol) or vol < 1e-6 * float(np.prod(ext)):
            raise TnfError(f"{where}: zero-volume mesh (volume {vol:.3g} m^3, extent {ext.tolist()})")


def select(
    spec: Any, object_names: Sequence[str] | None = None, single: str | None = None
) -> tuple[ObjectSource, list[str]]:
    """The object source of ``spec`` (the ``objects`` config, ``{name, **params}`` or a bare name) and the object
    names a run uses.

    ``single`` (one name, the ``object`` setting) wins over ``object_names`` (a list, or None for every object of
    the source). Unknown names raise a TnfError listing what is available.
    """

    source = OBJECTS.build(spec)
    source.name = split_spec(spec, "objects")[0]
    available = source.names()
    if not isinstance(available, list | tuple) or not all(isinstance(n, str) and n for n in available):
        raise TnfError(
            f"object source {source.name!r}: names() must return a list of non-empty strings, got "
            f"{_short_list([repr(n) for n in available]) if isinstance(available, list | tuple) else repr(available)}"
        )
    if not available:
        raise TnfError(f"object source {source.name!r} lists no objects (its names() is empty)")
    if single not in (None, ""):
        wanted: Sequence[str] = [str(single)]
    elif object_names is not None:
        wanted = [str(n) for n in object_names]
    else:
        wanted = available
    unknown = [n for n in wanted if n not in available]
    if unknown:
        fix = "object=NAME" if single not in (None, "") else "object_names=[NAME, ...], or object_names=null for all"
        raise TnfError(
            f"unknown object {unknown[0]!r} in source {source.name!r}; available: {_short_list(available)}; "
            f"choose with {fix}"
        )
    if not wanted:
        raise TnfError(f"no objects selected from source {source.name!r} (object_names is empty)")
    return source, list(dict.fromkeys(wanted))


def shard_of(index: Any, count: Any = 1) -> tuple[int, int] | None:
    """``(shard, shards)`` of a job in a sweep over object shards (``shard=I shards=N``), or None when the run
    takes every selected object (``index`` None). A bad pair raises a one-line TnfError."""
    if index in (None, ""):
        return None
    try:
        i, n = int(index), int(count)
    except (TypeError, ValueError):
        raise TnfError(f"shard and shards must be integers, got shard={index!r} shards={count!r}") from None
    if n < 1 or not 0 <= i < n:
        raise TnfError(f"shard must be in 0..shards-1 and shards >= 1, got shard={i} shards={n}")
    return i, n


def shard(names: Sequence[str], index: Any = None, count: Any = 1) -> list[str]:
    """This job's share of ``names``: names number ``index``, ``index + count``, ... (all of them when ``index``
    is None), for the ``shard`` and ``shards`` settings. The jobs ``shard=0..shards-1`` of one sweep select the
    same names in the same order, so their shares are disjoint and cover every name: each object is made by one
    job, and a rerun of the sweep redoes only what a killed job left unfinished (finished items are skipped)."""
    spec = shard_of(index, count)
    if spec is None:
        return list(names)
    i, n = spec
    return list(names)[i::n]


def _short_list(names: Sequence[str], limit: int = 40) -> str:
    if not names:
        return "none"
    head = ", ".join(names[:limit])
    return head + (f", ... ({len(names)} in all)" if len(names) > limit else "")
