"""Mesh modelling for the built-in objects: the building blocks that ``tnf.objects.builtin`` makes its objects of.

Solids (``lathe`` revolves a profile, ``extrude`` a polygon; ``sphere``, ``box``, ``cylinder``), booleans
(``union``, ``difference``), surface detail as vertex displacement (``radial``, ``along_normals``, with the
profiles ``knurl``, ``thread``, ``window``; ``subdivide`` gives them vertices to move) and vertex colours
(``paint``, ``bands``, ``speckle``, ``rgb``). Lengths are metres, z up; meshes are trimesh meshes.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

Array = np.ndarray
TAU = 2 * np.pi


def _resample(points: Any, step: float) -> Array:
    """A polyline ``[(r, z), ...]`` with extra points so that no segment is longer than ``step`` metres.

    The given points (corners) are kept, so sharp edges stay sharp.
    """
    p = np.asarray(points, dtype=float)
    out = [p[0]]
    for a, b in zip(p[:-1], p[1:]):
        n = max(1, int(np.ceil(np.linalg.norm(b - a) / step)))
        t = np.linspace(0, 1, n + 1)[1:, None]
        out.extend(a + (b - a) * t)
    return np.asarray(out)


def lathe(points: Any, sections: int = 64, step: float = 0.003):
    """Solid of revolution about +z from a profile ``[(r, z), ...]`` in metres.

    An open profile must start and end on the axis (r = 0); a closed one (first point == last) makes a
    hollow ring-shaped solid (cups, bowls, rolls of tape).
    """
    from trimesh.creation import revolve

    prof = _resample(points, step)
    mesh = revolve(prof, sections=sections)
    if mesh.volume < 0:
        mesh.invert()
    return mesh


def radial(mesh, fn: Callable[[Array, Array, Array], Array]):
    """Displace vertices away from the z axis by ``fn(theta, z, r)`` metres (vertices on the axis stay)."""
    v = mesh.vertices.copy()
    r = np.hypot(v[:, 0], v[:, 1])
    theta = np.arctan2(v[:, 1], v[:, 0])
    dr = np.where(r > 1e-6, fn(theta, v[:, 2], r), 0.0)
    scale = np.where(r > 1e-6, (r + dr) / np.maximum(r, 1e-9), 1.0)
    v[:, :2] *= scale[:, None]
    mesh.vertices = v
    return mesh


def along_normals(mesh, fn: Callable[[Array], Array]):
    """Displace vertices along their normals by ``fn(vertices) -> [N]`` metres (bumps > 0, dents < 0)."""
    n = mesh.vertex_normals.copy()
    mesh.vertices = mesh.vertices + n * fn(mesh.vertices)[:, None]
    return mesh


def sphere(radius: float, subdivisions: int = 4):
    import trimesh

    return trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)


def box(extents, at=(0, 0, 0)):
    import trimesh

    m = trimesh.creation.box(extents=extents)
    m.apply_translation(at)
    return m


def cylinder(radius: float, height: float, at=(0, 0, 0), sections: int = 32, axis: str = "z"):
    import trimesh

    m = trimesh.creation.cylinder(radius=radius, height=height, sections=sections)
    if axis == "x":
        m.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))
    elif axis == "y":
        m.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
    m.apply_translation(at)
    return m


def union(*meshes):
    import trimesh

    return trimesh.boolean.union(list(meshes), engine="manifold")


def difference(a, *cutters):
    import trimesh

    return trimesh.boolean.difference([a, *cutters], engine="manifold")


def extrude(polygon, height: float, z0: float = 0.0):
    """Extrude a shapely polygon (metres, xy) from ``z0`` up by ``height``."""
    import trimesh

    m = trimesh.creation.extrude_polygon(polygon, height)
    m.apply_translation([0, 0, z0])
    return m


def subdivide(mesh, max_edge: float):
    """Split faces until no edge is longer than ``max_edge`` metres (so displacement has vertices to move)."""
    import trimesh

    v, f = trimesh.remesh.subdivide_to_size(mesh.vertices, mesh.faces, max_edge=max_edge)
    return trimesh.Trimesh(v, f, process=True)


def rgb(hex_colour: str) -> Array:
    h = hex_colour.lstrip("#")
    return np.array([int(h[i : i + 2], 16) / 255 for i in (0, 2, 4)])


def paint(mesh, fn: Callable[[Array], Array]):
    """Vertex colours from ``fn(vertices [N,3]) -> [N,3]`` floats in [0, 1]; alpha is opaque."""
    c = np.clip(np.asarray(fn(mesh.vertices), dtype=float), 0, 1)
    if c.ndim == 1:
        c = np.broadcast_to(c, (len(mesh.vertices), 3))
    rgba = np.concatenate([np.round(c * 255), np.full((len(c), 1), 255.0)], axis=1).astype(np.uint8)
    mesh.visual.vertex_colors = rgba
    return mesh


def bands(values: Array, edges: list[float], colours: list[str]) -> Array:
    """Colour by which interval of ``edges`` each value falls in (``len(colours) == len(edges) + 1``)."""
    idx = np.searchsorted(np.asarray(edges), values)
    pal = np.stack([rgb(c) for c in colours])
    return pal[idx]


def speckle(v: Array, amount: float = 0.06, seed: int = 0) -> Array:
    """Deterministic per-vertex brightness noise in [-amount, amount], so flat colours show texture."""
    h = np.sin(v @ np.array([127.1, 311.7, 74.7]) * 97.0 + seed * 13.1) * 43758.5453
    return (h - np.floor(h) - 0.5) * 2 * amount


def knurl(theta: Array, z: Array, count: int, pitch: float, depth: float) -> Array:
    """A diamond knurl: two opposite helices of ``count`` ridges around, ``pitch`` metres along z."""
    a = np.cos(count * theta + TAU * z / pitch)
    b = np.cos(count * theta - TAU * z / pitch)
    return depth * 0.5 * (np.maximum(a, 0) ** 2 + np.maximum(b, 0) ** 2)


def thread(theta: Array, z: Array, pitch: float, depth: float) -> Array:
    """A single-start helical thread: a triangular wave of ``depth`` metres, ``pitch`` metres per turn."""
    phase = (z / pitch - theta / TAU) % 1.0
    return depth * (1 - 2 * np.abs(phase - 0.5))


def window(x: Array, lo: float, hi: float) -> Array:
    return ((x >= lo) & (x <= hi)).astype(float)
