"""Built-in objects, food: fruit, vegetables and a doughnut.

Each maker returns a closed trimesh in metres, z up, coloured per vertex (``tnf.objects.builtin``).
"""

from __future__ import annotations

import numpy as np

from tnf.objects.modelling import (
    TAU,
    along_normals,
    cylinder,
    lathe,
    paint,
    radial,
    rgb,
    speckle,
    sphere,
    union,
)


def banana():
    """A 20 cm banana: a curved, tapered tube with five flat faces, a stalk and a dark tip."""
    import trimesh

    n_len, n_around = 48, 20
    s = np.linspace(0, 1, n_len)
    ang = (s - 0.5) * 1.6
    R = 0.12
    centre = np.stack([R * np.sin(ang), np.zeros_like(s), R * (1 - np.cos(ang))], 1)
    tangent = np.stack([np.cos(ang), np.zeros_like(s), np.sin(ang)], 1)
    normal = np.stack([-np.sin(ang), np.zeros_like(s), np.cos(ang)], 1)
    binormal = np.cross(tangent, normal)
    rad = 0.018 * np.sin(np.pi * np.clip(s, 0.02, 0.98)) ** 0.6
    rad = np.where(s > 0.93, np.maximum(rad, 0.005), rad)  # the stalk
    phi = np.linspace(0, TAU, n_around, endpoint=False)
    # Five flat-ish faces with rounded ridges between them.
    prof = 1 + 0.08 * np.cos(5 * phi)
    ring = (np.cos(phi) * prof)[None, :, None] * normal[:, None] + (np.sin(phi) * prof)[None, :, None] * binormal[
        :, None
    ]
    verts = (centre[:, None] + rad[:, None, None] * ring).reshape(-1, 3)
    faces = []
    for i in range(n_len - 1):
        for j in range(n_around):
            a, b = i * n_around + j, i * n_around + (j + 1) % n_around
            c, d = a + n_around, b + n_around
            faces += [[a, c, b], [b, c, d]]
    start, end = len(verts), len(verts) + 1
    verts = np.vstack([verts, centre[0] - tangent[0] * 0.003, centre[-1] + tangent[-1] * 0.002])
    for j in range(n_around):
        faces.append([start, j, (j + 1) % n_around])
        base = (n_len - 1) * n_around
        faces.append([end, base + (j + 1) % n_around, base + j])
    m = trimesh.Trimesh(verts, np.array(faces), process=True)
    if m.volume < 0:
        m.invert()
    tip = np.concatenate([np.repeat(s, n_around), [0.0, 1.0]])
    col = np.where(
        (tip < 0.04)[:, None], rgb("#3b2a12"), np.where((tip > 0.9)[:, None], rgb("#6b8e23"), rgb("#f3d34a"))
    )
    m.visual.vertex_colors = np.concatenate(
        [np.round(np.clip(col + speckle(m.vertices, 0.05)[:, None], 0, 1) * 255), np.full((len(col), 1), 255)], 1
    ).astype(np.uint8)
    return m


def apple():
    """An 8 cm apple with a dimpled top, a stalk and faint vertical ribs."""
    t = np.linspace(0, np.pi, 28)
    r = 0.04 * np.sin(t) * (1 + 0.12 * np.sin(t) ** 2)
    z = -0.036 * np.cos(t) - 0.008 * np.sin(t) ** 8 + 0.006 * np.exp(-(((t - np.pi) / 0.35) ** 2))
    z[-1] = z[-1] - 0.012  # the dimple around the stalk
    pts = [(0, z[0] + 0.004), *zip(r[1:-1], z[1:-1]), (0, z[-1])]
    m = union(lathe(pts, sections=64), cylinder(0.0022, 0.022, at=(0.0, 0, z[-1] + 0.011), sections=12))
    radial(m, lambda th, zz, rr: 0.0012 * np.cos(5 * th) * (rr > 0.01))
    return paint(
        m,
        lambda v: np.where(
            (v[:, 2] > 0.026)[:, None] & (np.hypot(v[:, 0], v[:, 1]) < 0.003)[:, None],
            rgb("#5b3a1a"),
            rgb("#b3202a") + 0.25 * (v[:, 2:3] / 0.04) * rgb("#80a020"),
        ),
    )


def lemon():
    """A 9 cm lemon: an ellipsoid with pointed ends and a pitted peel."""
    m = sphere(1.0, 4)
    v = m.vertices
    tip = 1 + 0.25 * np.abs(v[:, 0]) ** 6
    m.vertices = np.stack([v[:, 0] * 0.04 * tip, v[:, 1] * 0.029, v[:, 2] * 0.029], 1)

    def pits(x):
        h = np.sin(x[:, 0] * 1700) * np.sin(x[:, 1] * 1500 + 2) * np.sin(x[:, 2] * 1600 + 1)
        return -0.0006 * (h > 0.3)

    along_normals(m, pits)
    return paint(m, lambda x: rgb("#f5d90a") + speckle(x, 0.05)[:, None])


def donut():
    """A 10 cm ring doughnut with raised sprinkles on its iced top."""
    import trimesh

    m = trimesh.creation.torus(0.032, 0.017, major_sections=64, minor_sections=28)

    def sprinkles(v):
        h = np.sin(v[:, 0] * 900) * np.sin(v[:, 1] * 1100 + 1)
        return 0.0012 * (h > 0.7) * (v[:, 2] > 0.006)

    along_normals(m, sprinkles)
    return paint(
        m,
        lambda v: (
            np.where((v[:, 2] > 0.005)[:, None], rgb("#e86fa0"), rgb("#c98b3f"))
            + np.where((sprinkles(v) > 0)[:, None], 0.4, 0.0)
        ),
    )


def cucumber():
    """A 22 cm cucumber with scattered warts, rounded ends and a darker stripe pattern."""
    m = sphere(1.0, 4)
    v = m.vertices
    m.vertices = np.stack([v[:, 0] * 0.11, v[:, 1] * 0.02, v[:, 2] * 0.021], 1)

    def warts(x):
        h = np.sin(x[:, 0] * 600) * np.sin(np.arctan2(x[:, 2], x[:, 1]) * 7)
        return 0.0018 * np.clip(h - 0.75, 0, None) / 0.25

    along_normals(m, warts)
    return paint(m, lambda x: rgb("#2f6b2a") + 0.12 * np.sin(np.arctan2(x[:, 2], x[:, 1]) * 10)[:, None])


def pepper():
    """A 9 cm bell pepper: four lobes, a furrowed top and a thick stem."""
    t = np.linspace(0.05, np.pi - 0.15, 24)
    pts = [(0, -0.04), *zip(0.038 * np.sin(t) ** 0.7, -0.04 * np.cos(t)), (0.012, 0.034), (0, 0.032)]
    m = lathe(pts, sections=72)
    radial(m, lambda th, z, r: -0.005 * np.abs(np.sin(2 * th)) ** 4 * (r > 0.01))
    stem = cylinder(0.005, 0.018, at=(0, 0, 0.042), sections=10)
    m = union(m, stem)
    return paint(m, lambda v: np.where((v[:, 2] > 0.034)[:, None], rgb("#3d7a2a"), rgb("#d6281b")))
