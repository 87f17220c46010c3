"""Built-in objects, containers: cans, bottles, cups, jars, boxes and tins.

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
