"""Built-in objects, tools and hardware: hand tools, fasteners, pens, a gear and kitchen tools.

Each maker returns a closed trimesh in metres, z up, coloured per vertex (``tnf.objects.builtin``).
"""

from __future__ import annotations

import numpy as np

from tnf.objects.modelling import (
    TAU,
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
    thread,
    union,
    window,
)


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


def rolling_pin():
    """A 25 cm rolling pin: a barrel with shallow grooves and two handles with a bead."""
    pts = [(0, -0.125), (0.011, -0.125), (0.012, -0.12), (0.012, -0.1), (0.014, -0.098), (0.01, -0.094)]
    pts += [(0.024, -0.085), (0.025, -0.082), (0.025, 0.082), (0.024, 0.085), (0.01, 0.094), (0.014, 0.098)]
    pts += [(0.012, 0.1), (0.012, 0.12), (0.011, 0.125), (0, 0.125)]
    m = lathe(pts, sections=48, step=0.0025)
    radial(m, lambda th, z, r: -0.001 * (np.cos(TAU * z / 0.02) > 0.9) * window(z, -0.08, 0.08))
    m.apply_transform(np.array([[0, 0, 1, 0], [0, 1, 0, 0], [-1, 0, 0, 0], [0, 0, 0, 1.0]]))
    return paint(m, lambda v: rgb("#d9a66b") + 0.06 * np.sin(v[:, 1:2] * 400) + speckle(v, 0.03)[:, None])


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
