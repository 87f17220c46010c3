"""``pybullet``: the objects that ship with ``pybullet_data`` (needs the optional extra: pip install tnf[assets]).

Names: ``random_000`` ... ``random_999`` (its ``random_urdfs/``, procedurally generated blobs) and the
textured assets (``duck``, ``teddy``, ``lego``, ``jenga``, ``domino``, ``mug``, ``soccerball``, ...). Each is
read from its URDF: the visual meshes with their scale and origin, coloured by the mesh's own texture when it
has one and otherwise by the URDF material colour.
"""

from __future__ import annotations

import logging
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from tnf.errors import TnfError
from tnf.objects import ObjectSource
from tnf.objects.mesh_dir import load_mesh_file
from tnf.registry import FROM_YAML, yaml_defaults

log = logging.getLogger(__name__)

# name -> URDF path inside pybullet_data
TEXTURED = {
    "duck": "duck_vhacd.urdf",
    "teddy": "teddy_vhacd.urdf",
    "soccerball": "soccerball.urdf",
    "lego": "lego/lego.urdf",
    "jenga": "jenga/jenga.urdf",
    "domino": "domino/domino.urdf",
    "mug": "objects/mug.urdf",
    "sphere": "sphere2.urdf",
    "cube": "cube_small.urdf",
}


def data_path() -> Path:
    """The ``pybullet_data`` folder, or a TnfError saying how to install it."""
    try:
        import pybullet_data
    except ImportError:
        raise TnfError(
            "the pybullet object source needs pybullet: pip install tnf[assets] (or pip install pybullet)"
        ) from None
    return Path(pybullet_data.getDataPath())


def _floats(text: str | None, n: int, default: float) -> np.ndarray:
    if not text:
        return np.full(n, default)
    vals = [float(x) for x in text.split()]
    return np.array(vals if len(vals) == n else vals[:1] * n)


def load_urdf_visual(urdf: Path):
    """The visual geometry of every link of ``urdf`` as one ``trimesh.Trimesh`` (link frames ignored beyond
    each visual's own origin, which suits the single-link objects of ``pybullet_data``)."""
    import trimesh

    try:
        root = ET.parse(urdf).getroot()
    except (ET.ParseError, OSError) as e:
        raise TnfError(f"cannot read URDF {urdf}: {e}") from None
    colours = {
        m.get("name"): _floats(c.get("rgba"), 4, 1.0)
        for m in root.findall("material")
        if (c := m.find("color")) is not None
    }
    parts = []
    for visual in root.iter("visual"):
        geom = visual.find("geometry")
        if geom is None:
            continue
        mesh_el, box_el, sph_el, cyl_el = (geom.find(k) for k in ("mesh", "box", "sphere", "cylinder"))
        if mesh_el is not None:
            fname = (mesh_el.get("filename") or "").replace("package://", "")
            part = load_mesh_file(urdf.parent / fname)
            part.apply_scale(_floats(mesh_el.get("scale"), 3, 1.0))
        elif box_el is not None:
            part = trimesh.creation.box(extents=_floats(box_el.get("size"), 3, 0.0))
        elif sph_el is not None:
            part = trimesh.creation.icosphere(3, radius=float(sph_el.get("radius", 0)))
        elif cyl_el is not None:
            part = trimesh.creation.cylinder(float(cyl_el.get("radius", 0)), float(cyl_el.get("length", 0)))
        else:
            continue
        origin = visual.find("origin")
        if origin is not None:
            xyz = _floats(origin.get("xyz"), 3, 0.0)
            rpy = _floats(origin.get("rpy"), 3, 0.0)
            tf = trimesh.transformations.euler_matrix(rpy[0], rpy[1], rpy[2], axes="sxyz")
            tf[:3, 3] = xyz
            part.apply_transform(tf)
        mat = visual.find("material")
        rgba = None
        if mat is not None:
            c = mat.find("color")
            rgba = _floats(c.get("rgba"), 4, 1.0) if c is not None else colours.get(mat.get("name"))
        if part.visual.kind != "texture" and rgba is not None:
            colour = np.round(np.clip(rgba, 0, 1) * 255).astype(np.uint8)
            part.visual = trimesh.visual.ColorVisuals(part, vertex_colors=np.tile(colour, (len(part.vertices), 1)))
        parts.append(part)
    if not parts:
        raise TnfError(f"{urdf}: empty mesh (no visual geometry)")
    return parts[0] if len(parts) == 1 else trimesh.util.concatenate(parts)


class PyBulletData(ObjectSource):
    """Objects of pybullet_data: random_urdfs blobs and textured assets (pip install tnf[assets])."""

    @dataclass
    @yaml_defaults("objects/pybullet")
    class Config:
        include_random: bool = FROM_YAML
        """Include the 1000 ``random_urdfs`` blobs (random_000 ... random_999)."""
        include_textured: bool = FROM_YAML
        """Include the textured assets (duck, teddy, lego, jenga, domino, mug, ...)."""
        scale: float = FROM_YAML
        """Multiplies every object's size (URDF units are metres)."""
        skip_invalid: bool = FROM_YAML
        """Leave out meshes that fail validation (e.g. random_urdfs/168), logging why."""

        def validate(self) -> None:
            if not self.scale > 0:
                raise ValueError(f"scale must be > 0, got {self.scale}")

    name = "pybullet"

    def __init__(self, cfg: Config | None = None):
        self.cfg = cfg or PyBulletData.Config()
        self.skip_invalid = self.cfg.skip_invalid
        self.root = data_path()
        self._urdfs: dict[str, Path] = {}
        if self.cfg.include_textured:
            for name, rel in TEXTURED.items():
                if (self.root / rel).is_file():
                    self._urdfs[name] = self.root / rel
        if self.cfg.include_random:
            for d in sorted((self.root / "random_urdfs").glob("[0-9]*")):
                if (d / f"{d.name}.urdf").is_file():
                    self._urdfs[f"random_{d.name}"] = d / f"{d.name}.urdf"

    def names(self) -> list[str]:
        return sorted(self._urdfs)

    def where(self, name: str) -> str:
        return str(self._urdfs.get(name, self.root / name))

    def _load(self, name: str):
        mesh = load_urdf_visual(self._urdfs[name])
        if self.cfg.scale != 1.0:
            mesh.apply_scale(self.cfg.scale)
        return mesh
