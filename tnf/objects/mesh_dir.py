"""``mesh_dir``: every mesh file in a folder (OBJ with MTL and textures, PLY, STL, GLB/GLTF, OFF).

Object names are file paths relative to the folder without the extension (``mugs/red``), except for the YCB
layout ``<object>/google_16k/textured.obj`` (and ``<object>/<kind>/textured.obj``), which is named
``<object>``. Textures that an MTL file names by a path outside the mesh's folder (``../textures/a.png``)
or by an absolute path are found too.
"""

from __future__ import annotations

import logging
import os
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Literal, cast

import numpy as np

from tnf.errors import TnfError
from tnf.objects import ObjectSource
from tnf.registry import FROM_YAML, yaml_defaults

if TYPE_CHECKING:
    from trimesh.resolvers import Resolver

log = logging.getLogger(__name__)

MESH_SUFFIXES = (".obj", ".ply", ".stl", ".glb", ".gltf", ".off")
# Preferred file of a YCB object folder, best first.
YCB_FILES = ("google_16k/textured.obj", "google_64k/textured.obj", "poisson/textured.obj", "tsdf/textured.obj")

UP_AXES = Literal["x", "y", "z", "-x", "-y", "-z"]


def up_to_z(axis: str) -> np.ndarray:
    """A 4x4 rotation taking the mesh's ``axis`` ('y', '-x', ...) to +z (tnf's up)."""
    import trimesh

    v = np.zeros(3)
    v["xyz".index(axis[-1])] = -1.0 if axis.startswith("-") else 1.0
    z = np.array([0.0, 0.0, 1.0])
    if np.allclose(v, z):
        return np.eye(4)
    if np.allclose(v, -z):
        return trimesh.transformations.rotation_matrix(np.pi, [1, 0, 0])
    axis3 = np.cross(v, z)
    return trimesh.transformations.rotation_matrix(np.pi / 2, axis3 / np.linalg.norm(axis3))


def load_mesh_file(path: str | os.PathLike[str], scale: float = 1.0, up_axis: str = "z"):
    """Load one mesh file as a single ``trimesh.Trimesh`` (scenes are concatenated), scaled and rotated to z up.

    Raises a TnfError naming the file when it is missing, unreadable or holds no triangles. The mesh is not
    centred or validated; :meth:`ObjectSource.load` does that.
    """
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise TnfError(f"mesh file not found: {path}")
    try:
        # Not processed while loading: processing silently drops NaN vertices, which validation must see.
        loaded = trimesh.load(path, process=False, resolver=cast("Resolver", _Resolver(path.parent)))
    except Exception as e:  # trimesh raises many kinds of errors for malformed files
        raise TnfError(f"cannot read mesh {path}: {type(e).__name__}: {e}") from None
    if isinstance(loaded, trimesh.Scene):
        geoms = [g for g in loaded.dump() if isinstance(g, trimesh.Trimesh)]
        if not geoms:
            raise TnfError(f"{path}: empty mesh (no triangles in the file)")
        mesh = geoms[0] if len(geoms) == 1 else cast("trimesh.Trimesh", trimesh.util.concatenate(geoms))
    elif isinstance(loaded, trimesh.Trimesh):
        mesh = loaded
    else:
        raise TnfError(f"{path}: empty mesh (a {type(loaded).__name__}, not triangles)")
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    if (len(v) and (v.ndim != 2 or v.shape[1] != 3)) or (len(f) and (f.ndim != 2 or f.shape[1] != 3)):
        raise TnfError(f"{path}: malformed mesh (vertices {v.shape}, faces {f.shape}; both need 3 columns)")
    if len(v) and np.isfinite(v).all():
        try:
            mesh.process()
        except Exception as e:  # degenerate input trips trimesh's vertex merging in some versions
            raise TnfError(f"cannot process mesh {path}: {type(e).__name__}: {e}") from None
    if scale != 1.0:
        mesh.apply_scale(scale)
    if up_axis != "z":
        mesh.apply_transform(up_to_z(up_axis))
    return mesh


class _Resolver:
    """Finds files an OBJ/MTL/GLTF names: relative to the mesh's folder (``..`` allowed), or absolute."""

    def __init__(self, folder: Path):
        self.folder = folder

    def get(self, name: str) -> bytes:
        name = name.strip().strip('"').replace("\\", "/")
        candidates = [Path(name)] if os.path.isabs(name) else []
        candidates += [self.folder / name, self.folder / Path(name).name]
        for p in candidates:
            if p.is_file():
                return p.read_bytes()
        raise FileNotFoundError(f"{name} (looked in {self.folder})")

    def __getitem__(self, name: str) -> bytes:
        return self.get(name)

    def namespaced(self, namespace: str) -> _Resolver:
        return _Resolver(self.folder / namespace)

    def keys(self):
        return (str(p.relative_to(self.folder)) for p in self.folder.rglob("*") if p.is_file())

    def write(self, name: str, data: bytes) -> None:  # pragma: no cover - loading never writes
        raise OSError("read-only")


def find_meshes(root: Path) -> dict[str, Path]:
    """Object name -> mesh file for every mesh under ``root`` (YCB folders named by their object)."""
    found: dict[str, Path] = {}
    ycb_dirs = set()
    for sub in sorted(p for p in root.iterdir() if p.is_dir()) if root.is_dir() else []:
        for rel in YCB_FILES:
            if (sub / rel).is_file():
                found[sub.name] = sub / rel
                ycb_dirs.add(sub)
                break
    for p in sorted(root.rglob("*")):
        if p.suffix.lower() not in MESH_SUFFIXES:
            continue
        if p.is_symlink() and not p.exists():
            log.warning("mesh_dir: skipping %s: a broken symbolic link (to %s)", p, os.readlink(p))
            continue
        if not p.is_file():
            continue
        if any(d in p.parents for d in ycb_dirs) or any(part.startswith(".") for part in p.relative_to(root).parts):
            continue
        name = p.relative_to(root).with_suffix("").as_posix()
        if name in found:  # same stem, different formats: keep the first (sorted) and say so
            log.warning("mesh_dir: %s and %s both give object %r; using the first", found[name], p, name)
            continue
        found[name] = p
    for name in found:  # `tools` and `tools/hammer`: one's results would lie inside the other's, and be replaced
        parts = name.split("/")
        outer = next((a for a in ("/".join(parts[:i]) for i in range(1, len(parts))) if a in found), None)
        if outer is not None:
            raise TnfError(
                f"objects.path: objects {outer!r} ({found[outer]}) and {name!r} ({found[name]}) would share a folder "
                f"of results; rename {found[outer].name} or the folder {outer}/"
            )
    return found


def _other(root: Path) -> str:
    """What ``root`` holds instead of meshes, for the error on a folder without any: '; it holds only .fbx (3)'."""
    files = [p for p in root.rglob("*") if not any(part.startswith(".") for part in p.relative_to(root).parts)]
    broken = sum(p.is_symlink() and not p.exists() for p in files)
    counts = Counter(p.suffix.lower() or "(no suffix)" for p in files if p.is_file())
    held = [f"{suffix} ({n})" for suffix, n in counts.most_common(5)] + ([f"broken links ({broken})"] if broken else [])
    return f"; it holds only {', '.join(held)}" if held else "; it is empty"


class MeshDir(ObjectSource):
    """Meshes from a folder (OBJ+MTL+textures, PLY, STL, GLB/GLTF), YCB layout included."""

    @dataclass
    @yaml_defaults("objects/mesh_dir")
    class Config:
        path: str = FROM_YAML
        """The folder of meshes (searched recursively)."""
        scale: float = FROM_YAML
        """Factor from file units to metres (0.001 for millimetres)."""
        up_axis: UP_AXES = FROM_YAML
        """The files' up axis; it is rotated to +z."""
        skip_invalid: bool = FROM_YAML
        """Leave out meshes that fail validation, logging why (false: such a mesh is an error)."""

        def validate(self) -> None:
            if not self.path:
                raise ValueError("path is required: the folder of meshes (objects.path=/data/ycb)")
            if not self.scale > 0:
                raise ValueError(f"scale must be > 0, got {self.scale}")

    name = "mesh_dir"

    def __init__(self, cfg: Config):
        self.cfg = cfg
        self.root = Path(cfg.path).expanduser()
        if not self.root.is_dir():
            raise TnfError(f"objects.path: mesh folder not found: {self.root}")
        self._files = find_meshes(self.root)
        self.skip_invalid = cfg.skip_invalid
        if not self._files:
            raise TnfError(
                f"objects.path: no mesh files ({', '.join(MESH_SUFFIXES)}) under {self.root}{_other(self.root)}"
            )

    def names(self) -> list[str]:
        return sorted(self._files)

    def where(self, name: str) -> str:
        return str(self._files.get(name, self.root / name))

    def file(self, name: str) -> Path:
        """The mesh file of object ``name``."""
        self.check_name(name)
        return self._files[name]

    def _load(self, name: str):
        return load_mesh_file(self._files[name], self.cfg.scale, self.cfg.up_axis)
