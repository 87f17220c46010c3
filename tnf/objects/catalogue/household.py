"""Built-in objects, household things: soap, a sponge, a candle and a roll of tape.

Each maker returns a closed trimesh in metres, z up, coloured per vertex (``tnf.objects.builtin``).
"""

from __future__ import annotations

import numpy as np

from tnf.objects.modelling import (
    TAU,
    along_normals,
    box,
    cylinder,
    lathe,
    paint,
    radial,
    rgb,
    speckle,
    sphere,
    subdivide,
    union,
)


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
