"""Where the poses of generated touches come from (``generate.directions``, ``generate.poses_file``).

Poses are camera-to-world matrices [N, 4, 4] of the sensor (metres, OpenGL: the sensor looks along its -z).
``sample_poses`` draws them on a sphere around the object (or inside the touch stage's held-out cone,
``pose_cone``), ``read_poses`` reads them from a file, and ``pose_source`` says which for the manifest.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from tnf.errors import TnfError
from tnf.generators.settings import GenerateSettings
from tnf.sim.touch import sphere_directions, start_poses


def read_poses(path: str | os.PathLike[str]) -> np.ndarray:
    """Camera-to-world poses [N, 4, 4] (metres, OpenGL) from ``.npy`` or ``.json`` (list, or ``{"poses": ...}``)."""
    p = Path(path).expanduser()
    if not p.is_file():
        raise TnfError(f"generate.poses_file not found: {p}")
    try:
        if p.suffix == ".npy":
            poses = np.load(p)
        else:
            data = json.loads(p.read_text())
            poses = np.asarray(data["poses"] if isinstance(data, dict) else data, dtype=np.float64)
    except (ValueError, KeyError, TypeError) as e:
        raise TnfError(f"generate.poses_file {p}: cannot read poses ({e})") from None
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4) or len(poses) == 0:
        raise TnfError(f"generate.poses_file {p}: expected [N, 4, 4] camera-to-world poses, got {poses.shape}")
    return poses


def sample_poses(
    n: int,
    radius: float,
    up: Any,
    random_roll: bool,
    seed: int,
    cone: tuple[Any, float] | None = None,
) -> np.ndarray:
    """``n`` poses on the sphere of ``radius`` metres, looking at the origin: [n, 4, 4] c2w.

    Directions are uniform on the whole sphere, or with ``cone`` = (axis, half-angle in degrees) uniform inside
    that cone (``generate.directions=novel_view``: the touch stage's held-out cone)."""

    rng = np.random.default_rng(seed)
    if cone is None:
        dirs = sphere_directions(rng, n, (0.0, 0.0, 1.0), 0.0, inside=False)
    else:
        dirs = sphere_directions(rng, n, cone[0], float(cone[1]), inside=True)
    return start_poses(rng, dirs, radius, up=list(up), random_roll=random_roll)


def pose_source(settings: GenerateSettings, sim: bool = False) -> dict[str, Any]:
    """Where the poses of generated touches came from, for their manifest: ``{"directions": "sphere"}``,
    ``{"directions": "novel_view", "cone_axis": [x, y, z], "cone_deg": d}``, ``{"directions": "file"}`` or
    ``{"directions": "sim"}`` (the simulated touches' own poses)."""
    if sim:
        return {"directions": "sim"}
    if settings.poses_file:
        return {"directions": "file"}
    cone = pose_cone(settings)
    if cone is None:
        return {"directions": "sphere"}
    return {"directions": "novel_view", "cone_axis": [float(a) for a in cone[0]], "cone_deg": cone[1]}


def pose_cone(settings: GenerateSettings) -> tuple[list[float], float] | None:
    """The cone that sampled directions come from (``generate.directions``): None for the whole sphere."""
    if settings.directions == "sphere":
        return None
    if settings.cone_deg == 0.0:  # sphere_directions would draw from the whole sphere; it checks range and axis
        raise TnfError(
            "generate.directions=novel_view needs a held-out cone: generate.cone_deg (from touch.novel_view_cone) is 0"
        )
    return list(settings.cone_axis), settings.cone_deg
