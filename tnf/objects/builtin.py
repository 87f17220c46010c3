"""``builtin``: a procedural library of rigid household-like objects, made by code with trimesh.

Every object is deterministic, 5-25 cm in size (the 5 mm bearing ball apart), in metres, z up, coloured per
vertex, and carries surface detail at the scale a fingertip sensor feels (2-20 mm): ridges, knurling, threads,
grooves, dimples, raised marks, holes, and both sharp and rounded edges, so that touches of different objects
look different.
Meshes are closed (watertight) and kept to a moderate triangle count so that ray casting and rendering stay
fast. Each object is generated once per process and copied on every ``load``. The building blocks (revolved
profiles, extrusions, booleans, displacements, colours) are in ``tnf.objects.modelling``.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from tnf.objects import ObjectSource
from tnf.objects.modelling import (
    TAU,
    along_normals,
    bands,
    box,
    cylinder,
    difference,
    extrude,
    knurl,
    lathe,
    paint,
    radial,
    rgb,
    speckle,
    sphere,
    subdivide,
    thread,
    union,
    window,
)
from tnf.registry import FROM_YAML, yaml_defaults


# -- the objects --------------------------------------------------------------------------------------------
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


def can():
    """A 12 cm drink can: rolled rims, a stack of circumferential beads, a printed band."""
    r, h = 0.033, 0.12
    pts = [(0, -h / 2), (r - 0.006, -h / 2), (r - 0.002, -h / 2 + 0.004), (r, -h / 2 + 0.012)]
    for z in np.linspace(-h / 2 + 0.02, h / 2 - 0.025, 9):
        pts += [(r, z - 0.003), (r - 0.0015, z), (r, z + 0.003)]
    pts += [(r, h / 2 - 0.014), (r - 0.004, h / 2 - 0.004), (r - 0.003, h / 2), (r - 0.0055, h / 2)]
    pts += [(r - 0.0055, h / 2 - 0.004), (0, h / 2 - 0.004)]
    m = lathe(pts, sections=64)
    return paint(
        m,
        lambda v: (
            bands(v[:, 2], [-0.045, 0.045], ["#c9ccd1", "#d21f3c", "#c9ccd1"])
            + 0.2 * window(np.cos(3 * np.arctan2(v[:, 1], v[:, 0])), 0.8, 1.0)[:, None]
        ),
    )


def bottle():
    """A 22 cm plastic bottle with a ribbed waist and a knurled screw cap."""
    pts = [(0, -0.11), (0.03, -0.11), (0.033, -0.105), (0.033, 0.03), (0.026, 0.06), (0.012, 0.075)]
    pts += [(0.012, 0.08), (0.0135, 0.081), (0.0135, 0.11), (0, 0.11)]
    m = lathe(pts, sections=64)

    def relief(theta, z, r):
        ribs = -0.002 * window(np.sin(TAU * z / 0.008), 0.0, 1.0) * window(z, -0.07, -0.02)
        cap = knurl(theta, z, 24, 0.03, 0.0012) * window(z, 0.083, 0.108)
        return ribs + cap

    radial(m, relief)
    return paint(m, lambda v: bands(v[:, 2], [-0.05, 0.0, 0.081], ["#3a8fd0", "#f4f4f4", "#3a8fd0", "#1b3b8a"]))


def wine_bottle():
    """A 25 cm glass bottle: long neck with a lip ring, an embossed label band."""
    pts = [(0, -0.125), (0.035, -0.125), (0.037, -0.12), (0.037, 0.03), (0.03, 0.055), (0.013, 0.075)]
    pts += [(0.0125, 0.11), (0.0155, 0.112), (0.0155, 0.118), (0.013, 0.12), (0.013, 0.125), (0, 0.125)]
    m = lathe(pts, sections=64)
    radial(m, lambda t, z, r: 0.0012 * window(z, -0.06, 0.0) * window(np.cos(TAU * z / 0.06 * 2), -2, 2))
    return paint(m, lambda v: bands(v[:, 2], [-0.06, 0.0, 0.1], ["#1f4a2a", "#efe6c8", "#1f4a2a", "#7a1020"]))


def mug():
    """A 9.5 cm mug with a rounded handle, a foot ring and a groove under the rim."""
    ro, ri, h = 0.042, 0.038, 0.095
    loop = [(ri, -h / 2 + 0.006), (ro - 0.004, -h / 2 + 0.006), (ro - 0.004, -h / 2), (ro, -h / 2 + 0.004)]
    loop += [(ro, h / 2 - 0.012), (ro - 0.0015, h / 2 - 0.01), (ro, h / 2 - 0.008), (ro, h / 2 - 0.001)]
    loop += [(ro - 0.002, h / 2), (ri, h / 2), (ri, -h / 2 + 0.006)]
    body = lathe(loop, sections=64)
    import trimesh

    handle = trimesh.creation.torus(0.026, 0.0065, major_sections=32, minor_sections=12)
    handle.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
    handle.apply_translation([ro + 0.008, 0, 0])
    inner = cylinder(ri + 0.001, h, sections=64)
    m = union(body, difference(handle, inner))
    return paint(
        m, lambda v: np.where((np.hypot(v[:, 0], v[:, 1]) < ri + 0.0005)[:, None], rgb("#f5f1e8"), rgb("#2e6e9e"))
    )


def bowl():
    """A 16 cm bowl: a foot ring, a thick rounded lip and fluted outer wall."""
    t = np.linspace(0, np.pi / 2, 12)
    outer = [(0.03, -0.035), (0.032, -0.04), (0.036, -0.04), (0.036, -0.034)]
    outer += [(0.036 + 0.044 * np.sin(a), -0.034 + 0.07 * (1 - np.cos(a))) for a in t[1:]]
    inner = [(0.074 * np.sin(a), -0.03 + 0.064 * (1 - np.cos(a))) for a in t[::-1]]
    loop = [*outer, (0.08, 0.04), (0.074, 0.04), *inner[:-1], (0.001, -0.03), (0.001, -0.035), outer[0]]
    m = lathe(loop, sections=72)
    radial(m, lambda th, z, r: 0.0015 * np.abs(np.cos(9 * th)) * window(z, -0.02, 0.025) * (r > 0.05))
    return paint(m, lambda v: bands(v[:, 2], [0.03], ["#d88a3c", "#6b3b1a"]) + speckle(v, 0.04)[:, None])


def paper_cup():
    """A 10 cm tapered cup with a rolled lip and a corrugated sleeve."""
    loop = [(0.026, -0.05), (0.0405, 0.044), (0.043, 0.046), (0.0435, 0.05), (0.041, 0.05), (0.0385, 0.046)]
    loop += [(0.0245, -0.045), (0.0, -0.045), (0.0, -0.05), (0.026, -0.05)]
    # The two axis points give a closed bottom disc rather than a hole.
    m = lathe([(0.0, -0.05), *loop[:-3], (0.0, -0.045)], sections=72)
    radial(m, lambda th, z, r: 0.0012 * np.cos(36 * th) ** 2 * window(z, -0.02, 0.02) * (r > 0.03))
    return paint(m, lambda v: bands(v[:, 2], [-0.02, 0.02], ["#ffffff", "#8b5a2b", "#ffffff"]))


def jar():
    """A 12 cm jar with a threaded neck and a knurled lid sitting above the thread."""
    pts = [(0, -0.06), (0.04, -0.06), (0.042, -0.056), (0.042, 0.02), (0.034, 0.03), (0.034, 0.05)]
    pts += [(0.038, 0.05), (0.038, 0.06), (0, 0.06)]
    m = lathe(pts, sections=72, step=0.002)
    radial(m, lambda th, z, r: thread(th, z, 0.005, 0.0015) * window(z, 0.031, 0.048) * (r < 0.036))
    radial(m, lambda th, z, r: knurl(th, z, 30, 0.02, 0.001) * window(z, 0.051, 0.059) * (r > 0.036))
    return paint(m, lambda v: bands(v[:, 2], [0.02, 0.0495], ["#a7c7a0", "#cfe3ca", "#d4a017"]))


def vase():
    """A 20 cm fluted vase with a flared mouth."""
    z = np.linspace(-0.1, 0.1, 30)
    r = 0.035 + 0.02 * np.sin((z + 0.1) / 0.2 * np.pi) ** 2 * (1 - (z + 0.1) / 0.35) + 0.01 * ((z + 0.1) / 0.2) ** 4
    loop = [(0.0, -0.1), *zip(r, z), (r[-1] - 0.004, 0.1), (0.02, 0.05), (0.0, 0.05)]
    m = lathe(loop, sections=96)
    radial(m, lambda th, zz, rr: -0.002 * np.abs(np.sin(8 * th)) * window(zz, -0.09, 0.085) * (rr > 0.03))
    return paint(m, lambda v: rgb("#4d7fa8") + 0.25 * np.sin(np.arctan2(v[:, 1], v[:, 0]) * 8)[:, None] ** 2)


def cereal_box():
    """A 25 x 18 x 6 cm carton with folded top seam and a raised panel on the front."""
    m = box([0.18, 0.06, 0.24])
    seam = box([0.18, 0.008, 0.01], at=(0, 0, 0.125))
    panel = box([0.12, 0.003, 0.10], at=(0, -0.031, 0.02))
    slot = box([0.06, 0.012, 0.004], at=(0, -0.03, 0.105))
    m = difference(union(m, seam, panel), slot)
    return paint(
        m, lambda v: np.where((v[:, 1] < -0.0305)[:, None], rgb("#f1c40f"), rgb("#c0392b")) + speckle(v)[:, None]
    )


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


def screwdriver():
    """A 22 cm screwdriver: fluted handle, a steel shaft and a flat tip."""
    pts = [(0, -0.11), (0.012, -0.11), (0.015, -0.105), (0.015, -0.01), (0.011, 0.0), (0.004, 0.005)]
    pts += [(0.0035, 0.1), (0.0035, 0.104), (0, 0.104)]
    m = lathe(pts, sections=48)
    radial(m, lambda th, z, r: -0.0025 * np.abs(np.cos(3 * th)) ** 3 * window(z, -0.1, -0.015) * (r > 0.01))
    tip = box([0.0065, 0.0012, 0.012], at=(0, 0, 0.108))
    m = union(m, tip)
    return paint(m, lambda v: bands(v[:, 2], [-0.105, 0.0], ["#222222", "#e8b400", "#b8bcc2"]))


def hammer():
    """A 25 cm hammer: a ringed grip, a round striking face and a split claw."""
    grip = lathe([(0, -0.125), (0.014, -0.125), (0.015, -0.12), (0.013, 0.05), (0.011, 0.1), (0, 0.1)], sections=40)
    radial(grip, lambda th, z, r: -0.0012 * (np.sin(TAU * z / 0.007) > 0.3) * window(z, -0.115, -0.03))
    head = box([0.07, 0.022, 0.026], at=(0.0, 0, 0.105))
    face = cylinder(0.015, 0.03, at=(0.045, 0, 0.105), axis="x")
    claw = box([0.05, 0.02, 0.012], at=(-0.055, 0, 0.112))
    slot = box([0.04, 0.005, 0.03], at=(-0.065, 0, 0.11))
    m = difference(union(grip, head, face, claw), slot)
    return paint(m, lambda v: np.where((v[:, 2] > 0.09)[:, None], rgb("#6d7178"), rgb("#c0392b")))


def wrench():
    """A 20 cm open-end wrench, 6 mm thick, with a ring end and a through hole."""
    from shapely.geometry import Point
    from shapely.geometry import box as sbox
    from shapely.ops import unary_union

    shaft = sbox(-0.075, -0.008, 0.075, 0.008)
    jaw = Point(0.085, 0).buffer(0.02, 24).difference(sbox(0.08, -0.007, 0.12, 0.007))
    ring = Point(-0.085, 0).buffer(0.018, 24).difference(Point(-0.085, 0).buffer(0.009, 6))
    slot = sbox(-0.04, -0.003, 0.04, 0.003)
    poly = unary_union([shaft, jaw, ring]).difference(slot)
    m = extrude(poly, 0.006, z0=-0.003)
    return paint(m, lambda v: rgb("#aab0b8") + speckle(v, 0.05)[:, None])


def bolt():
    """An 8 cm bolt: a hexagonal head with sharp edges and a threaded shank (2.5 mm pitch)."""
    shank = lathe([(0, -0.05), (0.007, -0.05), (0.008, -0.049), (0.008, 0.02), (0, 0.02)], sections=48, step=0.0008)
    radial(shank, lambda th, z, r: thread(th, z, 0.0025, 0.0012) * window(z, -0.048, 0.012))
    head = cylinder(0.013, 0.01, at=(0, 0, 0.024), sections=6)
    washer = cylinder(0.014, 0.0015, at=(0, 0, 0.0185), sections=40)
    m = union(shank, head, washer)
    return paint(m, lambda v: rgb("#8c9196") + speckle(v, 0.05)[:, None])


def hex_nut():
    """A 5 cm hexagonal nut, 2 cm thick, with a threaded hole and chamfered faces."""
    from shapely.geometry import Polygon

    hexagon = Polygon([(0.025 * np.cos(a), 0.025 * np.sin(a)) for a in np.arange(6) * TAU / 6])
    body = extrude(hexagon, 0.02, z0=-0.01)
    chamfer = lathe([(0, -0.011), (0.031, -0.011), (0.031, 0.011), (0, 0.011)], sections=6)
    cone = lathe(
        [(0, -0.012), (0.0235, -0.012), (0.033, -0.002), (0.033, 0.002), (0.0235, 0.012), (0, 0.012)], sections=48
    )
    hole = lathe([(0, -0.012), (0.011, -0.012), (0.011, 0.012), (0, 0.012)], sections=48, step=0.0008)
    radial(hole, lambda th, z, r: -thread(th, z, 0.003, 0.0015))
    m = difference(body, difference(chamfer, cone), hole)
    return paint(m, lambda v: rgb("#b5a642") + speckle(v, 0.05)[:, None])


def tape_roll():
    """An 11 cm roll of tape: a ring with a ridged cardboard core and a visible tape edge."""
    loop = [(0.038, -0.025), (0.055, -0.025), (0.055, 0.025), (0.038, 0.025), (0.038, -0.025)]
    m = lathe(loop, sections=72, step=0.002)
    radial(m, lambda th, z, r: -0.0008 * (np.sin(TAU * z / 0.004) > 0) * (r < 0.04))
    return paint(m, lambda v: np.where((np.hypot(v[:, 0], v[:, 1]) < 0.0395)[:, None], rgb("#a0764a"), rgb("#d9d2b0")))


def soap_bar():
    """A 9 x 6 cm soap bar: a rounded superellipsoid with an embossed oval and wavy grooves."""
    m = sphere(1.0, 4)
    u = m.vertices
    e = 0.35  # squareness: small values give flat faces with rounded edges

    def sq(x):
        return np.sign(x) * np.abs(x) ** e

    m.vertices = np.stack([sq(u[:, 0]) * 0.045, sq(u[:, 1]) * 0.03, sq(u[:, 2]) * 0.014], 1)

    def marks(v):
        top = (v[:, 2] > 0.012).astype(float)
        oval = np.abs(np.hypot(v[:, 0] / 0.03, v[:, 1] / 0.018) - 1) < 0.08
        waves = np.sin(TAU * (v[:, 0] + 0.004 * np.sin(TAU * v[:, 1] / 0.02)) / 0.006) > 0.6
        return 0.0015 * top * oval - 0.0008 * (v[:, 2] < -0.012) * waves

    along_normals(m, marks)
    return paint(m, lambda v: rgb("#e6b8d0") + speckle(v, 0.03)[:, None])


def sponge():
    """A 10 x 7 x 3.5 cm sponge: a porous yellow body with a green scouring layer of grooves."""
    m = subdivide(box([0.10, 0.07, 0.035]), 0.0025)

    def pores(v):
        h = np.sin(v[:, 0] * 1900) * np.sin(v[:, 1] * 2300) * np.sin(v[:, 2] * 2100 + 1)
        scour = (v[:, 2] > 0.017) * 0.0012 * (np.sin(TAU * v[:, 0] / 0.005) > 0)
        return -0.0012 * (h > 0.4) * (v[:, 2] < 0.01) + scour

    along_normals(m, pores)
    return paint(
        m, lambda v: np.where((v[:, 2] > 0.01)[:, None], rgb("#2e8b3a"), rgb("#f6d645")) + speckle(v, 0.08)[:, None]
    )


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


def flashlight():
    """A 17 cm flashlight: knurled grip, a wider head with a bezel, a tail button."""
    pts = [(0, -0.085), (0.008, -0.085), (0.008, -0.08), (0.014, -0.08), (0.015, -0.078), (0.015, 0.03)]
    pts += [(0.022, 0.05), (0.022, 0.078), (0.0235, 0.08), (0.0235, 0.085), (0, 0.085)]
    m = lathe(pts, sections=64, step=0.0015)
    radial(m, lambda th, z, r: knurl(th, z, 20, 0.024, 0.0012) * window(z, -0.07, 0.015))
    radial(m, lambda th, z, r: -0.0015 * (np.cos(12 * th) > 0.5) * window(z, 0.079, 0.085) * (r > 0.02))
    return paint(m, lambda v: np.where((v[:, 2] > 0.0845)[:, None], rgb("#e8f0ff"), rgb("#2b2b2f")))


def marker():
    """A 14 cm marker: a cap with a clip, a grip ring and a label."""
    pts = [(0, -0.07), (0.004, -0.07), (0.009, -0.062), (0.009, 0.02), (0.0095, 0.02), (0.0095, 0.068)]
    pts += [(0.008, 0.07), (0, 0.07)]
    m = lathe(pts, sections=40, step=0.002)
    radial(m, lambda th, z, r: 0.0007 * (np.sin(TAU * z / 0.003) > 0) * window(z, -0.055, -0.035))
    clip = box([0.003, 0.004, 0.04], at=(0.0105, 0, 0.045))
    m = union(m, clip)
    return paint(m, lambda v: bands(v[:, 2], [-0.06, 0.02], ["#222222", "#f0f0f0", "#1a5fd0"]))


def polish_tin():
    """A 9 cm tin, 3 cm high: a lid with an embossed ring, a seam and a turning key."""
    pts = [(0, -0.015), (0.043, -0.015), (0.044, -0.013), (0.044, 0.005), (0.045, 0.005), (0.045, 0.014)]
    pts += [(0.044, 0.015), (0.03, 0.015), (0.0295, 0.0165), (0.025, 0.0165), (0.0245, 0.015), (0, 0.015)]
    m = lathe(pts, sections=72, step=0.002)
    key = box([0.004, 0.02, 0.006], at=(0.046, 0, -0.004))
    m = union(m, key)
    return paint(m, lambda v: bands(v[:, 2], [0.005, 0.0149], ["#8d939a", "#c8102e", "#d4a017"]))


def pill_bottle():
    """A 9 cm pill bottle with a ribbed child-proof cap (vertical ribs, 3 mm apart)."""
    pts = [(0, -0.045), (0.018, -0.045), (0.019, -0.043), (0.019, 0.02), (0.021, 0.022), (0.021, 0.043)]
    pts += [(0.019, 0.045), (0, 0.045)]
    m = lathe(pts, sections=80)
    radial(m, lambda th, z, r: 0.001 * (np.cos(40 * th) > 0) * window(z, 0.023, 0.042))
    return paint(m, lambda v: bands(v[:, 2], [0.021], ["#e07b00", "#ffffff"]))


def spray_can():
    """A 20 cm spray can: a domed shoulder, a collar, a nozzle with a dimpled button."""
    pts = [(0, -0.1), (0.03, -0.1), (0.032, -0.096), (0.032, 0.04), (0.025, 0.062), (0.013, 0.066)]
    pts += [(0.013, 0.072), (0.009, 0.072), (0.009, 0.085), (0.0, 0.088)]
    m = lathe(pts, sections=64)
    nozzle = cylinder(0.002, 0.01, at=(0.009, 0, 0.08), axis="x", sections=12)
    m = difference(m, nozzle)
    return paint(m, lambda v: bands(v[:, 2], [-0.06, 0.03, 0.065], ["#b0b5ba", "#1d8348", "#b0b5ba", "#ffffff"]))


def pencil():
    """An 18 cm hexagonal pencil (sharp edges) with a sharpened tip and a metal band with rings."""
    body = lathe([(0, -0.075), (0.0045, -0.075), (0.0045, 0.075), (0, 0.075)], sections=6)
    tip = lathe([(0, 0.074), (0.0055, 0.074), (0.0008, 0.1), (0, 0.1)], sections=24)
    band = lathe([(0, -0.09), (0.0042, -0.09), (0.0042, -0.074), (0, -0.074)], sections=24, step=0.001)
    radial(band, lambda th, z, r: 0.0004 * (np.sin(TAU * z / 0.003) > 0) * window(z, -0.088, -0.076))
    m = union(body, tip, band)
    m.apply_translation([0, 0, -0.005])
    return paint(m, lambda v: bands(v[:, 2], [-0.079, 0.069, 0.086], ["#c0c3c7", "#f2c200", "#e8c9a0", "#333333"]))


def gear():
    """An 8 cm gear, 1.5 cm thick: 16 sharp teeth, a keyed bore and lightening holes."""
    from shapely.geometry import Point, Polygon
    from shapely.ops import unary_union

    n = 16
    pts = []
    for i in range(n):
        a = i * TAU / n
        for da, r in ((-0.35, 0.033), (-0.18, 0.04), (0.18, 0.04), (0.35, 0.033)):
            pts.append((r * np.cos(a + da * TAU / n), r * np.sin(a + da * TAU / n)))
    poly = Polygon(pts)
    bore = unary_union(
        [Point(0, 0).buffer(0.008, 16), Polygon([(0.006, -0.002), (0.011, -0.002), (0.011, 0.002), (0.006, 0.002)])]
    )
    holes = [Point(0.02 * np.cos(a), 0.02 * np.sin(a)).buffer(0.005, 12) for a in np.arange(4) * TAU / 4 + 0.4]
    m = extrude(poly.difference(bore).difference(unary_union(holes)), 0.015, z0=-0.0075)
    return paint(m, lambda v: rgb("#7d8a99") + speckle(v, 0.05)[:, None])


def star_block():
    """A 9 cm five-pointed star block, 2.5 cm thick, with a raised star on top."""
    from shapely.geometry import Polygon

    def star(ro, ri):
        a = np.arange(10) * TAU / 10 + np.pi / 2
        r = np.where(np.arange(10) % 2 == 0, ro, ri)
        return Polygon(np.stack([r * np.cos(a), r * np.sin(a)], 1))

    m = union(extrude(star(0.047, 0.02), 0.025, z0=-0.0125), extrude(star(0.025, 0.011), 0.003, z0=0.012))
    return paint(m, lambda v: np.where((v[:, 2] > 0.0126)[:, None], rgb("#ffffff"), rgb("#e74c3c")))


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


def shampoo():
    """A 19 cm shampoo bottle with an oval section, a flip cap with a hinge groove and side grips."""
    m = lathe([(0, -0.095), (0.028, -0.095), (0.03, -0.09), (0.03, 0.06), (0.022, 0.075), (0, 0.075)], sections=64)
    v = m.vertices.copy()
    v[:, 1] *= 0.55
    m.vertices = v
    radial(
        m, lambda th, z, r: -0.0012 * (np.sin(TAU * z / 0.006) > 0) * window(z, -0.04, 0.0) * (np.abs(np.cos(th)) > 0.9)
    )
    cap = lathe([(0, 0.074), (0.017, 0.074), (0.017, 0.092), (0.015, 0.095), (0, 0.095)], sections=48, step=0.002)
    radial(cap, lambda th, z, r: -0.001 * window(z, 0.086, 0.088))
    m = union(m, cap)
    return paint(
        m,
        lambda v: np.where(
            (v[:, 2] > 0.075)[:, None], rgb("#f5f5f5"), rgb("#7b3fa0") + 0.3 * window(v[:, 2], -0.06, 0.03)[:, None]
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


def rolling_pin():
    """A 25 cm rolling pin: a barrel with shallow grooves and two handles with a bead."""
    pts = [(0, -0.125), (0.011, -0.125), (0.012, -0.12), (0.012, -0.1), (0.014, -0.098), (0.01, -0.094)]
    pts += [(0.024, -0.085), (0.025, -0.082), (0.025, 0.082), (0.024, 0.085), (0.01, 0.094), (0.014, 0.098)]
    pts += [(0.012, 0.1), (0.012, 0.12), (0.011, 0.125), (0, 0.125)]
    m = lathe(pts, sections=48, step=0.0025)
    radial(m, lambda th, z, r: -0.001 * (np.cos(TAU * z / 0.02) > 0.9) * window(z, -0.08, 0.08))
    m.apply_transform(np.array([[0, 0, 1, 0], [0, 1, 0, 0], [-1, 0, 0, 0], [0, 0, 0, 1.0]]))
    return paint(m, lambda v: rgb("#d9a66b") + 0.06 * np.sin(v[:, 1:2] * 400) + speckle(v, 0.03)[:, None])


def candle():
    """A 12 cm pillar candle with a scalloped melted rim, a wick and drip ridges."""
    pts = [(0, -0.06), (0.032, -0.06), (0.035, -0.057), (0.035, 0.055), (0.03, 0.05), (0.0, 0.05)]
    m = lathe(pts, sections=64)
    radial(
        m, lambda th, z, r: 0.0015 * np.clip(np.cos(6 * th), 0, None) * np.clip((z + 0.01) / 0.06, 0, 1) * (r > 0.033)
    )
    wick = cylinder(0.0012, 0.012, at=(0, 0, 0.055), sections=8)
    m = union(m, wick)
    return paint(
        m,
        lambda v: np.where(
            (v[:, 2] > 0.051)[:, None] & (np.hypot(v[:, 0], v[:, 1]) < 0.002)[:, None], rgb("#222222"), rgb("#f4ecd8")
        ),
    )


def cheese_grater():
    """A 14 cm box grater: a square tube with grating holes on two faces and a handle bar."""
    outer = box([0.07, 0.05, 0.14])
    inner = box([0.064, 0.044, 0.15])
    holes = [
        cylinder(0.003, 0.01, at=(x, -0.025, z), axis="y", sections=10)
        for x in np.arange(-0.024, 0.025, 0.012)
        for z in np.arange(-0.055, 0.056, 0.012)
    ]
    slots = [box([0.05, 0.01, 0.003], at=(0, 0.025, z)) for z in np.arange(-0.05, 0.051, 0.014)]
    handle = box([0.05, 0.01, 0.008], at=(0, 0, 0.074))
    m = union(difference(outer, inner, *holes, *slots), handle)
    return paint(m, lambda v: np.where((v[:, 2] > 0.0705)[:, None], rgb("#1c1c1c"), rgb("#c8ccd0")))


# name -> generator. `ball` and `box` stay cheap: the tiny debug config uses them.
MAKERS: dict[str, Callable[[], Any]] = {
    "apple": apple,
    "ball": ball,
    "banana": banana,
    "bearing_ball": bearing_ball,
    "bolt": bolt,
    "bottle": bottle,
    "bowl": bowl,
    "box": box_,
    "brick": brick,
    "can": can,
    "candle": candle,
    "cereal_box": cereal_box,
    "cheese_grater": cheese_grater,
    "chess_pawn": chess_pawn,
    "cucumber": cucumber,
    "die": die,
    "donut": donut,
    "flashlight": flashlight,
    "gear": gear,
    "golf_ball": golf_ball,
    "hammer": hammer,
    "hex_nut": hex_nut,
    "jar": jar,
    "lemon": lemon,
    "marker": marker,
    "mug": mug,
    "paper_cup": paper_cup,
    "pencil": pencil,
    "pepper": pepper,
    "pill_bottle": pill_bottle,
    "polish_tin": polish_tin,
    "puzzle_cube": puzzle_cube,
    "rolling_pin": rolling_pin,
    "shampoo": shampoo,
    "soap_bar": soap_bar,
    "sponge": sponge,
    "spray_can": spray_can,
    "star_block": star_block,
    "tape_roll": tape_roll,
    "tennis_ball": tennis_ball,
    "traffic_cone": traffic_cone,
    "vase": vase,
    "wine_bottle": wine_bottle,
    "wrench": wrench,
}


@functools.cache
def _make(name: str):
    mesh = MAKERS[name]()
    mesh.metadata["name"] = name
    return mesh


def describe(name: str) -> str:
    """The one-line description of built-in object ``name``."""
    doc = (MAKERS[name].__doc__ or "").strip().splitlines()
    return doc[0] if doc else name


class Builtin(ObjectSource):
    """Procedural household objects (bottles, cans, mugs, tools, fruit...) with fingertip-scale detail."""

    @dataclass
    @yaml_defaults("objects/builtin")
    class Config:
        scale: float = FROM_YAML
        """Multiplies every object's size (1.0: objects are 5-25 cm)."""

        def validate(self) -> None:
            if not self.scale > 0:
                raise ValueError(f"scale must be > 0, got {self.scale}")

    name = "builtin"

    def __init__(self, cfg: Config | None = None):
        self.cfg = cfg or Builtin.Config()

    def names(self) -> list[str]:
        return sorted(MAKERS)

    def where(self, name: str) -> str:
        return f"builtin object {name!r} (tnf/objects/builtin.py)"

    def _load(self, name: str):
        mesh = _make(name).copy()
        if self.cfg.scale != 1.0:
            mesh.apply_scale(self.cfg.scale)
        return mesh
