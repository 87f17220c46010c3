"""Built-in objects, toys and shapes: balls, dice, bricks, blocks, a cone and a chess pawn.

Each maker returns a closed trimesh in metres, z up, coloured per vertex (``tnf.objects.builtin``).
"""

from __future__ import annotations

import numpy as np

from tnf.objects.modelling import (
    TAU,
    along_normals,
    bands,
    box,
    cylinder,
    difference,
    extrude,
    lathe,
    paint,
    radial,
    rgb,
    speckle,
    sphere,
    union,
    window,
)


def ball():
    """A 7 cm rubber ball with a raised seam (baseball-like curve)."""
    m = sphere(0.035, 4)

    def seam(v):
        u = v / np.linalg.norm(v, axis=1, keepdims=True)
        # Distance from a saddle curve on the sphere: z = 0.5 sin(2 phi).
        phi = np.arctan2(u[:, 1], u[:, 0])
        d = np.abs(u[:, 2] - 0.5 * np.sin(2 * phi))
        return 0.0025 * np.exp(-((d / 0.05) ** 2))

    along_normals(m, seam)
    return paint(m, lambda v: np.where((seam(v) > 0.001)[:, None], rgb("#b01818"), rgb("#f2efe4")))


def box_():
    """A 10 x 7 x 5 cm box with a raised rim on the lid and a notch on one side."""
    m = box([0.10, 0.07, 0.05])
    lid = box([0.09, 0.06, 0.003], at=(0, 0, 0.0265))
    hole = box([0.092, 0.062, 0.01], at=(0, 0, 0.0295))
    rim = difference(box([0.10, 0.07, 0.006], at=(0, 0, 0.028)), hole)
    notch = box([0.02, 0.01, 0.012], at=(0, -0.035, 0.0))
    m = difference(union(m, lid, rim), notch)
    return paint(m, lambda v: bands(v[:, 2], [0.0245], ["#c08a4a", "#8a5a2b"]) + speckle(v)[:, None])


def die():
    """A 6 cm die with rounded pips (dimples) on every face."""
    m = box([0.06, 0.06, 0.06])
    pips = []
    layouts = {
        1: [(0, 0)],
        2: [(-1, -1), (1, 1)],
        3: [(-1, -1), (0, 0), (1, 1)],
        4: [(-1, -1), (-1, 1), (1, -1), (1, 1)],
    }
    layouts[5] = [*layouts[4], (0, 0)]
    layouts[6] = [*layouts[4], (-1, 0), (1, 0)]
    faces = [(1, 0, 1), (6, 0, -1), (2, 1, 1), (5, 1, -1), (3, 2, 1), (4, 2, -1)]
    for n, axis, sign in faces:
        for a, b in layouts[n]:
            c = np.zeros(3)
            c[axis] = sign * 0.032
            c[(axis + 1) % 3], c[(axis + 2) % 3] = a * 0.016, b * 0.016
            s = sphere(0.006, 2)
            s.apply_translation(c)
            pips.append(s)
    m = difference(m, union(*pips))
    return paint(m, lambda v: np.where((np.abs(v).max(1) < 0.0295)[:, None], rgb("#111111"), rgb("#f4f4f4")))


def brick():
    """A 6.4 x 3.2 cm toy brick with eight studs on top and a hollow underside."""
    m = box([0.064, 0.032, 0.019])
    cav = box([0.058, 0.026, 0.016], at=(0, 0, -0.0025))
    studs = [
        cylinder(0.0048, 0.0034, at=(-0.024 + 0.016 * i, -0.008 + 0.016 * j, 0.0112))
        for i in range(4)
        for j in range(2)
    ]
    tubes = [cylinder(0.0065, 0.016, at=(-0.016 + 0.016 * i, 0, -0.0025)) for i in range(3)]
    holes = [cylinder(0.0048, 0.017, at=(-0.016 + 0.016 * i, 0, -0.0025)) for i in range(3)]
    m = difference(union(difference(m, cav), *tubes, *studs), *holes)
    return paint(m, lambda v: rgb("#d01010") + speckle(v, 0.03)[:, None])


def bearing_ball():
    """A 5 mm steel bearing ball: a round indenter, like the balls that calibration presses use."""
    m = sphere(0.0025, 3)
    return paint(m, lambda v: rgb("#b4b8bd") + speckle(v / 0.01, 0.04)[:, None])


def golf_ball():
    """A 6 cm ball covered in round dimples 6 mm across."""
    m = sphere(0.03, 4)
    centres = sphere(1.0, 2).vertices  # 162 evenly spread dimple centres

    def dimples(v):
        u = v / np.linalg.norm(v, axis=1, keepdims=True)
        d = np.arccos(np.clip(u @ centres.T, -1, 1)).min(1) * 0.03
        return -0.0012 * np.clip(1 - (d / 0.0032) ** 2, 0, None)

    along_normals(m, dimples)
    return paint(m, lambda v: rgb("#f7f7f2") + speckle(v, 0.03)[:, None])


def tennis_ball():
    """A 6.6 cm ball with two grooved seams."""
    m = sphere(0.033, 4)

    def groove(v):
        u = v / np.linalg.norm(v, axis=1, keepdims=True)
        phi = np.arctan2(u[:, 1], u[:, 0])
        d = np.abs(u[:, 2] - 0.6 * np.cos(2 * phi))
        return -0.0015 * np.exp(-((d / 0.06) ** 2))

    along_normals(m, groove)
    return paint(m, lambda v: np.where((groove(v) < -0.0007)[:, None], rgb("#ffffff"), rgb("#c8e03a")))


def puzzle_cube():
    """A 5.7 cm puzzle cube: 3x3 cubies separated by 1 mm grooves, coloured stickers."""
    m = box([0.057, 0.057, 0.057])
    cuts = []
    for axis in range(3):
        for off in (-0.0095, 0.0095):
            ext = [0.07, 0.07, 0.07]
            ext[axis] = 0.0012
            at = [0.0, 0.0, 0.0]
            at[axis] = off
            cuts.append(difference(box(ext, at=at), box([0.053] * 3)))
    m = difference(m, *cuts)
    palette = np.stack([rgb(c) for c in ("#c41e3a", "#ff5800", "#009e60", "#0051ba", "#ffd500", "#ffffff")])

    def colour(v):
        axis = np.abs(v).argmax(1)
        sign = (np.take_along_axis(v, axis[:, None], 1)[:, 0] > 0).astype(int)
        c = palette[axis * 2 + sign]
        return np.where((np.abs(v).max(1) < 0.0283)[:, None], rgb("#111111"), c)

    return paint(m, colour)


def star_block():
    """A 9 cm five-pointed star block, 2.5 cm thick, with a raised star on top."""
    from shapely.geometry import Polygon

    def star(ro, ri):
        a = np.arange(10) * TAU / 10 + np.pi / 2
        r = np.where(np.arange(10) % 2 == 0, ro, ri)
        return Polygon(np.stack([r * np.cos(a), r * np.sin(a)], 1))

    m = union(extrude(star(0.047, 0.02), 0.025, z0=-0.0125), extrude(star(0.025, 0.011), 0.003, z0=0.012))
    return paint(m, lambda v: np.where((v[:, 2] > 0.0126)[:, None], rgb("#ffffff"), rgb("#e74c3c")))


def traffic_cone():
    """A 20 cm traffic cone on a square base with raised rings and stripes."""
    cone = lathe([(0, -0.09), (0.05, -0.09), (0.012, 0.1), (0, 0.1)], sections=48, step=0.004)
    radial(cone, lambda th, z, r: 0.0015 * window(z, -0.03, -0.02) + 0.0015 * window(z, 0.03, 0.04))
    base = box([0.13, 0.13, 0.01], at=(0, 0, -0.095))
    m = union(cone, base)
    return paint(
        m,
        lambda v: bands(
            v[:, 2], [-0.0301, -0.0199, 0.0299, 0.0401], ["#ff6a00", "#ffffff", "#ff6a00", "#ffffff", "#ff6a00"]
        ),
    )


def chess_pawn():
    """A 9 cm chess pawn: a stepped base, a sharp collar and a round head."""
    t = np.linspace(0, np.pi, 14)
    head = [(0.013 * np.sin(a), 0.03 - 0.013 * np.cos(a)) for a in t]
    pts = [(0, -0.045), (0.025, -0.045), (0.025, -0.039), (0.021, -0.037), (0.021, -0.032), (0.016, -0.028)]
    pts += [(0.008, 0.01), (0.014, 0.012), (0.014, 0.015), (0.007, 0.017), *head[1:-1], (0, 0.043)]
    m = lathe(pts, sections=56, step=0.002)
    return paint(m, lambda v: rgb("#f0e2c0") + speckle(v, 0.04)[:, None])
