"""``warp_gel``: a tactile simulator in NVIDIA Warp: a gel pressed with a constant force, shaded by the sensor's lights.

One call simulates a batch of touches of one object (a ``wp.Mesh`` built once per object) in a few kernel
launches, on the ``cpu`` or a ``cuda`` warp device with the same code:

1. **Height field.** From every pixel's point on the undeformed gel (``Sensor.gel_points``) a ray is cast along
   the sensor's axis (-z); ``t`` is the distance to the object. The sensor first touches the object after
   advancing ``t_min = min t``; the gap under each pixel is then ``g = t - t_min``. The rays are parallel, so
   for a rigid sensor pose the cast is done as an orthographic rasterisation of the mesh in the sensor frame
   (same hits, far cheaper than one BVH query per pixel); scaled poses use ``wp.mesh_query_ray``.
2. **Constant-force press.** After advancing a further ``d`` (the penetration), the contact area follows the
   method of dimensionality reduction for elastic contact: it is the area where ``g <= d / 2`` (exact for a
   paraboloid, Hertz ``a = sqrt(R d)``; exact for a flat punch). The normal force follows from the incremental
   stiffness of an elastic half-space, ``dF/dd = 2 E* a`` with ``a = sqrt(A / pi)``, stiffened for a thin layer
   of thickness ``h`` by ``1 + 1.33 (a/h) + 1.33 (a/h)^3`` (bonded thin-layer correction). ``F(d)`` is tabulated
   from a histogram of gaps and inverted for the target force: a sphere then obeys Hertz,
   ``F = 4/3 E* sqrt(R) d^1.5``.
3. **Deformation.** Where in contact the gel takes the object's shape (indentation ``u = d - g``). Around the
   contact the surface falls off smoothly: a screened membrane equation ``lap(u) = u / lambda^2`` (``lambda`` a
   multiple of the gel thickness) relaxed on a coarse grid with the contact as a constraint, upsampled with
   cubic B-splines.
4. **Shading.** Normals of the deformed surface, lit by the sensor's coloured point lights (diffuse + specular,
   ``Sensor.shade``); the difference to the undeformed gel's shading is blurred and added to the sensor's
   background, then Gaussian noise (drawn from a unit-variance table of normal quantiles). With no contact the
   image is the background plus noise.

A calibrated sensor (``sensor.calibration``, written by ``tnf calibrate``) replaces step 4's lights with its
measured shading table (colour change by surface slope), and brings its own blur, noise, background and the
gel's fall-off length. ``press_heights(..., penetration=d)`` presses to a given depth instead of a force, as
calibration presses are given.

Outputs (``TouchBatch``): 8-bit RGB images, indentation maps (metres), contact masks, the achieved force (N),
the penetration ``d`` (m), the first-contact point and the sensor pose at contact.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import warp as wp

from tnf.errors import TnfError
from tnf.registry import FROM_YAML, yaml_defaults
from tnf.runtime import check_memory, init_warp
from tnf.sensors.base import Sensor
from tnf.sim.base import Simulator, TouchBatch

MISS = 1.0e9  # ray distance stored for pixels that see no object (and pixels outside the gel)
SENSOR_BYTES_PER_PIXEL = 400
"""Host memory per image pixel of what a simulator holds and builds once (the gel's grids, shading, background),
a generous estimate."""
TOUCH_BYTES_PER_PIXEL = 80
"""Memory per image pixel of one touch of a batch (device buffers and the host copies of the results)."""


# -- kernels ------------------------------------------------------------------------------------------
# Per-pixel kernels take ``span``: each thread handles ``span`` consecutive columns of one image row. On the CPU a
# warp launch runs its threads one after another, and a thread per row (span = W) avoids a per-thread cost that
# would otherwise exceed the work of the cheap kernels; on a GPU span = 1 (a thread per pixel, coalesced).
wp.set_module_options({"enable_backward": False})  # forward only: no gradients are taken; halves compile time

NOISE_TABLE = 4096  # entries of the inverse normal CDF used to draw image noise


@wp.kernel
def _rasterize(
    verts: wp.array(dtype=wp.vec3),
    tris: wp.array(dtype=wp.int32),
    w2c: wp.array(dtype=wp.mat44),
    points: wp.array2d(dtype=wp.vec3),
    gel: wp.array2d(dtype=wp.uint8),
    to_px: wp.vec4,
    z_front: float,
    max_t: float,
    t_out: wp.array3d(dtype=float),
    t_min: wp.array(dtype=float),
):
    # The gel's rays are parallel (along the sensor's -z), so casting them equals rasterising the mesh in the
    # sensor frame with an orthographic projection and a depth test: one thread per (touch, triangle) visits
    # the pixel centres its projection covers. Hits and distances are those of ``_raycast`` (t in [0, max_t)).
    b, f = wp.tid()
    m = w2c[b]
    pa = wp.transform_point(m, verts[tris[3 * f]])
    pb = wp.transform_point(m, verts[tris[3 * f + 1]])
    pc = wp.transform_point(m, verts[tris[3 * f + 2]])
    if wp.min(wp.min(pa[2], pb[2]), pc[2]) > z_front:
        return  # entirely behind the gel's frontmost ray origin: every t would be negative
    hh = t_out.shape[1]
    ww = t_out.shape[2]
    # Pixel centre (row, col) sits at x = (col - to_px[1]) / to_px[0], y = (row - to_px[3]) / to_px[2].
    xlo = wp.min(wp.min(pa[0], pb[0]), pc[0]) * to_px[0] + to_px[1]
    xhi = wp.max(wp.max(pa[0], pb[0]), pc[0]) * to_px[0] + to_px[1]
    ylo = wp.max(wp.max(pa[1], pb[1]), pc[1]) * to_px[2] + to_px[3]  # to_px[2] < 0: highest y, lowest row
    yhi = wp.min(wp.min(pa[1], pb[1]), pc[1]) * to_px[2] + to_px[3]
    c0 = int(wp.ceil(wp.clamp(xlo - 0.01, -1.0, float(ww))))
    c1 = int(wp.floor(wp.clamp(xhi + 0.01, -1.0, float(ww))))
    r0 = int(wp.ceil(wp.clamp(ylo - 0.01, -1.0, float(hh))))
    r1 = int(wp.floor(wp.clamp(yhi + 0.01, -1.0, float(hh))))
    c0 = wp.max(c0, 0)
    r0 = wp.max(r0, 0)
    c1 = wp.min(c1, ww - 1)
    r1 = wp.min(r1, hh - 1)
    if c0 > c1 or r0 > r1:
        return
    area = (pb[0] - pa[0]) * (pc[1] - pa[1]) - (pb[1] - pa[1]) * (pc[0] - pa[0])
    if area == 0.0:
        return  # seen edge-on: a ray parallel to the triangle does not hit it
    inv = 1.0 / area
    eps = -1.0e-5  # barycentric slack so that pixel centres on shared edges are never lost
    for r in range(r0, r1 + 1):
        for c in range(c0, c1 + 1):
            if gel[r, c] != wp.uint8(0):
                p = points[r, c]
                w0 = ((pb[0] - p[0]) * (pc[1] - p[1]) - (pb[1] - p[1]) * (pc[0] - p[0])) * inv
                w1 = ((pc[0] - p[0]) * (pa[1] - p[1]) - (pc[1] - p[1]) * (pa[0] - p[0])) * inv
                w2 = ((pa[0] - p[0]) * (pb[1] - p[1]) - (pa[1] - p[1]) * (pb[0] - p[0])) * inv
                if w0 >= eps and w1 >= eps and w2 >= eps:
                    z = (w0 * pa[2] + w1 * pb[2] + w2 * pc[2]) / (w0 + w1 + w2)
                    tv = p[2] - z
                    if tv >= 0.0 and tv < max_t:
                        wp.atomic_min(t_out, b, r, c, tv)
                        wp.atomic_min(t_min, b, tv)


@wp.kernel
def _take_gaps(
    gaps: wp.array3d(dtype=float),
    gel: wp.array2d(dtype=wp.uint8),
    t_out: wp.array3d(dtype=float),
    t_min: wp.array(dtype=float),
):
    # press_heights: given gaps as ray distances; MISS where not finite or outside the gel.
    b, r, c = wp.tid()
    g = gaps[b, r, c]
    t = float(MISS)
    if gel[r, c] != wp.uint8(0) and wp.isfinite(g):
        t = wp.min(g, float(MISS))
    t_out[b, r, c] = t
    if t < MISS:
        wp.atomic_min(t_min, b, t)


@wp.kernel
def _raycast(
    mesh: wp.uint64,
    c2w: wp.array(dtype=wp.mat44),
    points: wp.array2d(dtype=wp.vec3),
    gel: wp.array2d(dtype=wp.uint8),
    max_t: float,
    t_out: wp.array3d(dtype=float),
    t_min: wp.array(dtype=float),
):
    # Used for sensor poses that are not rigid (scaled), where rays are not orthographic in the sensor frame.
    b, r, c = wp.tid()
    t = float(MISS)
    if gel[r, c] != wp.uint8(0):
        m = c2w[b]
        o = wp.transform_point(m, points[r, c])
        d = wp.normalize(wp.transform_vector(m, wp.vec3(0.0, 0.0, -1.0)))
        q = wp.mesh_query_ray(mesh, o, d, max_t)
        if q.result:
            t = q.t
    t_out[b, r, c] = t
    if t < MISS:
        wp.atomic_min(t_min, b, t)


@wp.kernel
def _gap_histogram(
    t: wp.array3d(dtype=float),
    t_min: wp.array(dtype=float),
    bin_width: float,
    c2w: wp.array(dtype=wp.mat44),
    points: wp.array2d(dtype=wp.vec3),
    span: int,
    hist: wp.array2d(dtype=wp.int32),
    first: wp.array(dtype=wp.vec3),
):
    # Histogram of the gaps g = t - t_min, and the world point of the first contact (the pixel with t = t_min).
    b, r, j = wp.tid()
    tm = t_min[b]
    if tm >= MISS:
        return
    c0 = j * span
    c1 = wp.min(c0 + span, t.shape[2])
    for c in range(c0, c1):
        tv = t[b, r, c]
        if tv < MISS:
            k = int((tv - tm) / bin_width)
            if k < hist.shape[1]:
                wp.atomic_add(hist, b, k, wp.int32(1))
            if tv == tm:
                m = c2w[b]
                o = wp.transform_point(m, points[r, c])
                d = wp.normalize(wp.transform_vector(m, wp.vec3(0.0, 0.0, -1.0)))
                first[b] = o + d * tv


@wp.func
def _stiffness(area: float, e_star: float, thickness: float) -> float:
    # dF/dd = 2 E* a, a = sqrt(area / pi), stiffened for a thin bonded layer by 1 + 1.33 (a/h) + 1.33 (a/h)^3.
    a = wp.sqrt(area / wp.pi)
    s = a / thickness
    return 2.0 * e_star * a * (1.0 + 1.33 * s + 1.33 * s * s * s)


@wp.kernel
def _solve_force(
    hist: wp.array2d(dtype=wp.int32),
    target: wp.array(dtype=float),
    t_min: wp.array(dtype=float),
    bin_width: float,
    pixel_area: float,
    e_star: float,
    thickness: float,
    depth: wp.array(dtype=float),
    force: wp.array(dtype=float),
):
    # One thread per touch: integrate dF/dd = 2 E* a f(a/h) over d in steps of 2 * bin_width (the contact
    # area at penetration d is the area with gap <= d / 2) until the target force is reached.
    b = wp.tid()
    depth[b] = 0.0
    force[b] = 0.0
    if t_min[b] >= MISS:
        return
    f_target = target[b]
    f = wp.float32(0.0)
    below = wp.float32(0.0)  # pixels in bins before the current one
    step = 2.0 * bin_width
    n = hist.shape[1]
    for k in range(n):
        cnt = float(hist[b, k])
        df = _stiffness((below + 0.5 * cnt) * pixel_area, e_star, thickness) * step
        if f + df >= f_target and df > 0.0:
            frac = (f_target - f) / df
            depth[b] = (float(k) + frac) * step
            force[b] = f_target
            return
        f += df
        below += cnt
    depth[b] = float(n) * step  # the sensor's deepest press did not reach the target force
    force[b] = f


@wp.kernel
def _force_at_depth(
    hist: wp.array2d(dtype=wp.int32),
    target_depth: wp.array(dtype=float),
    t_min: wp.array(dtype=float),
    bin_width: float,
    pixel_area: float,
    e_star: float,
    thickness: float,
    depth: wp.array(dtype=float),
    force: wp.array(dtype=float),
):
    # A press to a given penetration instead of a given force: the same integral as ``_solve_force``, stopped
    # at the target depth. ``press_heights`` refuses depths past max_penetration, the deepest the histogram
    # covers; the clamp only absorbs rounding.
    b = wp.tid()
    depth[b] = 0.0
    force[b] = 0.0
    if t_min[b] >= MISS:
        return
    step = 2.0 * bin_width
    n = hist.shape[1]
    d = wp.clamp(target_depth[b], 0.0, float(n) * step)
    f = wp.float32(0.0)
    below = wp.float32(0.0)
    for k in range(n):
        lo = float(k) * step
        if lo >= d:
            break
        cnt = float(hist[b, k])
        f += _stiffness((below + 0.5 * cnt) * pixel_area, e_star, thickness) * wp.min(d - lo, step)
        below += cnt
    depth[b] = d
    force[b] = f


@wp.kernel
def _coarse_constraint(
    t: wp.array3d(dtype=float),
    t_min: wp.array(dtype=float),
    depth: wp.array(dtype=float),
    factor: int,
    span: int,
    cval: wp.array3d(dtype=float),
    cmask: wp.array3d(dtype=wp.uint8),
    relax: wp.array3d(dtype=float),
):
    b, i, jb = wp.tid()
    d = depth[b]
    tm = t_min[b]
    j0 = jb * span
    j1 = wp.min(j0 + span, cval.shape[2])
    for j in range(j0, j1):
        hit = wp.int32(0)
        total = wp.float32(0.0)
        count = wp.int32(0)
        if d > 0.0:
            for di in range(factor):
                for dj in range(factor):
                    r = i * factor + di
                    c = j * factor + dj
                    if r < t.shape[1] and c < t.shape[2]:
                        tv = t[b, r, c]
                        g = tv - tm
                        if tv < MISS and g <= 0.5 * d:
                            hit = 1
                            total += d - g
                            count += 1
        cmask[b, i, j] = wp.uint8(hit)
        v = wp.float32(0.0)
        if count > 0:
            v = total / float(count)
        cval[b, i, j] = v
        relax[b, i, j] = v


@wp.kernel
def _relax_step(
    src: wp.array3d(dtype=float),
    cval: wp.array3d(dtype=float),
    cmask: wp.array3d(dtype=wp.uint8),
    screen: float,
    span: int,
    dst: wp.array3d(dtype=float),
):
    # Jacobi step of lap(u) = u / lambda^2 with u fixed in contact cells and u = 0 beyond the gel's rim.
    b, i, jb = wp.tid()
    h = src.shape[1]
    w = src.shape[2]
    j0 = jb * span
    j1 = wp.min(j0 + span, w)
    for j in range(j0, j1):
        if cmask[b, i, j] != wp.uint8(0):
            dst[b, i, j] = cval[b, i, j]
        else:
            s = wp.float32(0.0)
            if i > 0:
                s += src[b, i - 1, j]
            if i < h - 1:
                s += src[b, i + 1, j]
            if j > 0:
                s += src[b, i, j - 1]
            if j < w - 1:
                s += src[b, i, j + 1]
            dst[b, i, j] = s / (4.0 + screen)


@wp.func
def _bspline(f: float, k: int) -> float:
    if k == 0:
        return (1.0 - f) * (1.0 - f) * (1.0 - f) / 6.0
    if k == 1:
        return (3.0 * f * f * f - 6.0 * f * f + 4.0) / 6.0
    if k == 2:
        return (-3.0 * f * f * f + 3.0 * f * f + 3.0 * f + 1.0) / 6.0
    return f * f * f / 6.0


@wp.func
def _column_sum(relax: wp.array3d(dtype=float), b: int, i0: int, wr: wp.vec4, j: int) -> float:
    # B-spline-weighted sum of coarse rows i0-1 .. i0+2 in coarse column j (both clamped to the grid).
    hc = relax.shape[1]
    jj = wp.clamp(j, 0, relax.shape[2] - 1)
    acc = wp.float32(0.0)
    for ki in range(4):
        acc += wr[ki] * relax[b, wp.clamp(i0 - 1 + ki, 0, hc - 1), jj]
    return acc


@wp.kernel
def _compose(
    t: wp.array3d(dtype=float),
    t_min: wp.array(dtype=float),
    depth: wp.array(dtype=float),
    relax: wp.array3d(dtype=float),
    factor: int,
    span: int,
    u_out: wp.array3d(dtype=float),
    contact: wp.array3d(dtype=wp.uint8),
):
    b, r, jb = wp.tid()
    d = depth[b]
    tm = t_min[b]
    c0 = jb * span
    c1 = wp.min(c0 + span, t.shape[2])
    # Smooth fall-off: cubic B-spline of the coarse relaxed field (cell centres at (k + 0.5) * factor - 0.5),
    # evaluated separably: the vertical pass is shared by the pixels between two coarse columns.
    fk = float(factor)
    gr = (float(r) + 0.5) / fk - 0.5
    i0 = int(wp.floor(gr))
    fr = gr - float(i0)
    wr = wp.vec4(_bspline(fr, 0), _bspline(fr, 1), _bspline(fr, 2), _bspline(fr, 3))
    prev = wp.int32(-1000000)
    s0 = wp.float32(0.0)
    s1 = wp.float32(0.0)
    s2 = wp.float32(0.0)
    s3 = wp.float32(0.0)
    for c in range(c0, c1):
        tv = t[b, r, c]
        g = tv - tm
        inter = d - g  # how far the object reaches past the undeformed gel
        if tv >= MISS:
            inter = -1.0
        in_contact = d > 0.0 and tv < MISS and g <= 0.5 * d
        gc = (float(c) + 0.5) / fk - 0.5
        j0 = int(wp.floor(gc))
        fc = gc - float(j0)
        if j0 != prev:
            s0 = _column_sum(relax, b, i0, wr, j0 - 1)
            s1 = _column_sum(relax, b, i0, wr, j0)
            s2 = _column_sum(relax, b, i0, wr, j0 + 1)
            s3 = _column_sum(relax, b, i0, wr, j0 + 2)
            prev = j0
        acc = _bspline(fc, 0) * s0 + _bspline(fc, 1) * s1 + _bspline(fc, 2) * s2 + _bspline(fc, 3) * s3
        # Inside the contact the smoothed field lies below the object (smoothing lowers peaks), so the max takes
        # the object's shape there and blends into the fall-off at the contact's edge without a kink.
        u = wp.max(wp.max(acc, 0.0), inter)
        if d <= 0.0:
            u = 0.0
        u_out[b, r, c] = u
        contact[b, r, c] = wp.uint8(1) if in_contact else wp.uint8(0)


@wp.func
def _unit(v: wp.vec3) -> wp.vec3:
    # v / |v| with one division (wp.normalize divides each component); v is never near zero here.
    return v * (1.0 / wp.sqrt(wp.dot(v, v)))


@wp.func
def _power(x: float, e: float, ie: int) -> float:
    # x^e; by repeated squaring when the exponent is a small whole number (ie >= 0), far cheaper than pow.
    if ie < 0:
        return wp.pow(x, e)
    out = wp.float32(1.0)
    base = x
    n = ie
    while n > 0:
        if (n & 1) != 0:
            out = out * base
        base = base * base
        n = n >> 1
    return out


@wp.func
def _slope(h0: wp.array2d(dtype=float), u: wp.array3d(dtype=float), b: int, r: int, c: int, dx: float, dy: float):
    # Slope (dh/dx, dh/dy) of the deformed gel's outward height h = h0 - u at pixel (r, c): central differences,
    # one-sided at the border (``Sensor.surface_slopes`` on the host). Rows grow toward -y.
    hh = u.shape[1]
    ww = u.shape[2]
    rm = wp.max(r - 1, 0)
    rp = wp.min(r + 1, hh - 1)
    cm = wp.max(c - 1, 0)
    cp = wp.min(c + 1, ww - 1)
    sx = (h0[r, cp] - u[b, r, cp] - h0[r, cm] + u[b, r, cm]) / (float(cp - cm) * dx)
    sy = (h0[rm, c] - u[b, rm, c] - h0[rp, c] + u[b, rp, c]) / (float(rp - rm) * dy)
    return wp.vec2(sx, sy)


@wp.kernel
def _shade(
    u: wp.array3d(dtype=float),
    h0: wp.array2d(dtype=float),
    xy: wp.array2d(dtype=wp.vec2),
    gel: wp.array2d(dtype=wp.uint8),
    base: wp.array2d(dtype=wp.vec3),
    light_pos: wp.array(dtype=wp.vec3),
    light_rad: wp.array(dtype=wp.vec3),
    cam_dist: float,
    dx: float,
    dy: float,
    ambient: float,
    diffuse: float,
    specular: float,
    shininess: float,
    int_shininess: int,
    contrast: float,
    span: int,
    diff: wp.array3d(dtype=wp.vec3),
):
    b, r, jb = wp.tid()
    ww = u.shape[2]
    c0 = jb * span
    c1 = wp.min(c0 + span, ww)
    for c in range(c0, c1):
        if gel[r, c] == wp.uint8(0):
            diff[b, r, c] = wp.vec3(0.0)
        else:
            # Outward height of the deformed gel; the surface is z = -(cam_dist + height), its normal (sx, sy, 1).
            sl = _slope(h0, u, b, r, c, dx, dy)
            n = _unit(wp.vec3(sl[0], sl[1], 1.0))
            p2 = xy[r, c]
            p = wp.vec3(p2[0], p2[1], -(cam_dist + h0[r, c] - u[b, r, c]))
            view = _unit(-p)
            col = wp.vec3(ambient, ambient, ambient)
            for k in range(light_pos.shape[0]):
                ldir = _unit(light_pos[k] - p)
                ndl = wp.max(wp.dot(n, ldir), 0.0)
                half = _unit(ldir + view)
                ndh = wp.max(wp.dot(n, half), 0.0)
                col += light_rad[k] * (diffuse * ndl + specular * _power(ndh, shininess, int_shininess))
            diff[b, r, c] = contrast * (col - base[r, c])


@wp.func
def _table_axis(s: float, max_slope: float, power: float) -> float:
    # A slope's place along a table axis, in [-1, 1] (``tnf.sensors.calibration.table_cells``).
    t = wp.clamp(s, -max_slope, max_slope) / max_slope
    if power != 1.0:
        t = wp.sign(t) * wp.pow(wp.abs(t), power)
    return t


@wp.func
def _table(table: wp.array2d(dtype=wp.vec3), sx: float, sy: float, max_slope: float, power: float) -> wp.vec3:
    # Bilinear read of a calibration's shading table at slope (sx, sy), clamped to the grid (as
    # ``Calibration.shade`` reads it on the host).
    n = table.shape[0]
    fx = (_table_axis(sx, max_slope, power) + 1.0) / 2.0 * float(n - 1)
    fy = (_table_axis(sy, max_slope, power) + 1.0) / 2.0 * float(n - 1)
    j0 = wp.clamp(int(wp.floor(fx)), 0, n - 2)
    i0 = wp.clamp(int(wp.floor(fy)), 0, n - 2)
    ax = fx - float(j0)
    ay = fy - float(i0)
    top = table[i0, j0] * (1.0 - ax) + table[i0, j0 + 1] * ax
    bot = table[i0 + 1, j0] * (1.0 - ax) + table[i0 + 1, j0 + 1] * ax
    return top * (1.0 - ay) + bot * ay


@wp.kernel
def _shade_table(
    u: wp.array3d(dtype=float),
    h0: wp.array2d(dtype=float),
    gel: wp.array2d(dtype=wp.uint8),
    table: wp.array2d(dtype=wp.vec3),
    base: wp.array2d(dtype=wp.vec3),
    max_slope: float,
    power: float,
    dx: float,
    dy: float,
    span: int,
    diff: wp.array3d(dtype=wp.vec3),
):
    # Calibrated shading: the table at the deformed surface's slope minus ``base``, the table at the undeformed
    # slope (computed once on the host, as the lit undeformed gel is for ``_shade``).
    b, r, jb = wp.tid()
    c0 = jb * span
    c1 = wp.min(c0 + span, u.shape[2])
    for c in range(c0, c1):
        if gel[r, c] == wp.uint8(0):
            diff[b, r, c] = wp.vec3(0.0)
        else:
            sl = _slope(h0, u, b, r, c, dx, dy)
            diff[b, r, c] = _table(table, sl[0], sl[1], max_slope, power) - base[r, c]


@wp.kernel
def _blur_rows(
    src: wp.array3d(dtype=wp.vec3), weights: wp.array(dtype=float), span: int, dst: wp.array3d(dtype=wp.vec3)
):
    b, r, jb = wp.tid()
    rad = (weights.shape[0] - 1) // 2
    ww = src.shape[2]
    c0 = jb * span
    c1 = wp.min(c0 + span, ww)
    for c in range(c0, c1):
        acc = wp.vec3(0.0)
        for k in range(weights.shape[0]):
            cc = wp.clamp(c + k - rad, 0, ww - 1)
            acc += weights[k] * src[b, r, cc]
        dst[b, r, c] = acc


@wp.kernel
def _blur_cols_finish(
    src: wp.array3d(dtype=wp.vec3),
    weights: wp.array(dtype=float),
    background: wp.array2d(dtype=wp.vec3),
    noise_table: wp.array(dtype=float),
    noise_std: float,
    seed: int,
    b0: int,
    span: int,
    image: wp.array4d(dtype=wp.uint8),
):
    # Vertical blur of the difference image, added to the background with Gaussian noise, rounded to 8 bits.
    # Noise: three draws per pixel from an inverse normal CDF table (unit variance), indexed by 12 random bits.
    b, r, jb = wp.tid()
    rad = (weights.shape[0] - 1) // 2
    hh = src.shape[1]
    ww = src.shape[2]
    c0 = jb * span
    c1 = wp.min(c0 + span, ww)
    for c in range(c0, c1):
        acc = wp.vec3(0.0)
        for k in range(weights.shape[0]):
            rr = wp.clamp(r + k - rad, 0, hh - 1)
            acc += weights[k] * src[b, rr, c]
        v = background[r, c] + acc
        if noise_std > 0.0:
            state = wp.rand_init(seed, ((b0 + b) * hh + r) * ww + c)  # b0: first touch of this part
            n0 = noise_table[int(wp.randu(state) >> wp.uint32(20))]
            n1 = noise_table[int(wp.randu(state) >> wp.uint32(20))]
            n2 = noise_table[int(wp.randu(state) >> wp.uint32(20))]
            v = v + noise_std * wp.vec3(n0, n1, n2)
        for k in range(3):
            image[b, r, c, k] = wp.uint8(int(wp.clamp(v[k] + 0.5, 0.0, 255.0)))


# -- the simulator ------------------------------------------------------------------------------------
def _normal_quantiles(n: int) -> np.ndarray:
    """``[n]`` float32 standard normal quantiles at probabilities ``(k + 0.5) / n``, rescaled to unit variance.

    Drawing a uniform index into this table gives Gaussian noise up to 1/n quantile resolution, at a fraction of
    the cost of a Box-Muller transform per value.
    """
    from statistics import NormalDist

    q = np.array([NormalDist().inv_cdf((k + 0.5) / n) for k in range(n)])
    return (q / np.sqrt(np.mean(q**2))).astype(np.float32)


class WarpGel(Simulator):
    """Elastic gel pressed with a constant force, ray cast and shaded in NVIDIA Warp (CPU or CUDA)."""

    unhashed = ("cpu_threads",)

    @dataclass
    @yaml_defaults("simulator/warp_gel")
    class Config:
        histogram_bins: int = FROM_YAML
        """Resolution of the gap histogram that tabulates force against penetration (bins over max_penetration)."""
        coarse_factor: int = FROM_YAML
        """Downsampling of the grid on which the fall-off around the contact is relaxed (pixels per cell)."""
        relax_iterations: int = FROM_YAML
        """Jacobi iterations of the fall-off relaxation."""
        falloff: float = FROM_YAML
        """Decay length of the gel's deformation around the contact, as a multiple of the gel thickness."""
        max_distance: float = FROM_YAML
        """Longest ray cast from the gel toward the object, metres."""
        cpu_threads: int = FROM_YAML
        """Threads that share a batch on the ``cpu`` device (warp runs each CPU launch on one thread); 1 = off."""

        def validate(self) -> None:
            if self.histogram_bins < 8:
                raise ValueError(f"histogram_bins must be >= 8, got {self.histogram_bins}")
            if self.coarse_factor < 1:
                raise ValueError(f"coarse_factor must be >= 1, got {self.coarse_factor}")
            if self.relax_iterations < 0:
                raise ValueError(f"relax_iterations must be >= 0, got {self.relax_iterations}")
            if self.cpu_threads < 1:
                raise ValueError(f"cpu_threads must be >= 1, got {self.cpu_threads}")
            if self.falloff <= 0 or self.max_distance <= 0:
                raise ValueError("falloff and max_distance must be > 0")

    def __init__(self, cfg: Config, sensor: Sensor, device: str = "cpu"):
        """``sensor``: the tactile sensor to simulate; ``device``: warp device (``cpu``, ``cuda:0``)."""
        self.cfg = cfg
        self.sensor = sensor
        c = sensor.cfg
        check_memory(
            SENSOR_BYTES_PER_PIXEL * sensor.width * sensor.height,
            f"sensor {sensor.name!r}",
            f"sensor.width={c.width}, sensor.height={c.height}",
        )
        init_warp()
        self.device = wp.get_device(device)
        s = sensor
        h0 = s.gel_surface().astype(np.float32)
        x, y = s.gel_grid()
        gel = s.gel_mask()
        base = s.shade(s.gel_points(h0), s.surface_normals(h0)).astype(np.float32)
        bg = s.background().astype(np.float32)
        pos, rad = s.light_arrays()
        dev = self.device
        self._points = wp.array(s.gel_points(h0), dtype=wp.vec3, device=dev)
        self._xy = wp.array(np.stack([x, y], -1), dtype=wp.vec2, device=dev)
        self._h0 = wp.array(h0, dtype=float, device=dev)
        self._gel = wp.array(gel.astype(np.uint8), dtype=wp.uint8, device=dev)
        self._base = wp.array(base, dtype=wp.vec3, device=dev)
        self._base_np = base
        self._background = wp.array(bg, dtype=wp.vec3, device=dev)
        self.background = bg.astype(np.uint8)
        self._light_pos = wp.array(pos, dtype=wp.vec3, device=dev)
        self._light_rad = wp.array(rad, dtype=wp.vec3, device=dev)
        # A calibrated sensor brings measured optics: a shading table, blur, noise and the gel's fall-off.
        cal = s.calibration
        self.calibration = cal
        self.falloff = cal.falloff if cal is not None else cfg.falloff
        self.noise_std = cal.noise_std if cal is not None else s.cfg.noise_std
        self._table = self._table_base = None
        if cal is not None:
            self._table = wp.array(cal.table, dtype=wp.vec3, device=dev)
            self._table_base = wp.array(cal.shade(s.surface_slopes(h0)), dtype=wp.vec3, device=dev)
        sigma = cal.blur_sigma if cal is not None else s.cfg.blur_sigma
        if sigma > 0:
            radius = max(1, int(math.ceil(3 * sigma)))
            k = np.exp(-0.5 * (np.arange(-radius, radius + 1) / sigma) ** 2)
            self._blur = wp.array((k / k.sum()).astype(np.float32), dtype=float, device=dev)
        else:
            self._blur = None
        self._no_blur = wp.array(np.ones(1, np.float32), dtype=float, device=dev)
        self._noise_table = wp.array(_normal_quantiles(NOISE_TABLE), dtype=float, device=dev)
        # Pixel centre (row, col) from sensor-frame (x, y): col = x * fx / d + cx - 0.5, row = -y * fy / d + cy - 0.5.
        fx, fy, cx, cy = s.intrinsics()
        dist = s.cfg.camera_distance
        self._to_px = wp.vec4(fx / dist, cx - 0.5, -fy / dist, cy - 0.5)
        self._z_front = float(-(dist + h0[gel].min())) if gel.any() else -dist
        shin = float(s.cfg.shininess)
        self._int_shininess = int(shin) if shin.is_integer() and 0 <= shin <= 1024 else -1
        # Columns per thread of the per-pixel kernels (see the note above the kernels).
        self._span = 1 if self.device.is_cuda else s.width
        self._meshes: dict[int, tuple[Any, wp.Mesh, wp.array, wp.array]] = {}
        self._buffers: dict[str, Any] = {}
        self.timings: dict[str, float] | None = None
        """Set to ``{}`` to accumulate seconds per phase of ``press`` (synchronises the device; for benchmarks)."""
        self._last = 0.0

    def _phase(self, part: int, name: str) -> None:
        if self.timings is None or part != 0:
            return  # with a batch split over threads, the phases are those of the first part
        wp.synchronize_device(self.device)
        now = time.perf_counter()
        self.timings[name] = self.timings.get(name, 0.0) + now - self._last
        self._last = now

    # -- meshes -------------------------------------------------------------------------------------
    def mesh(self, mesh: Any) -> wp.Mesh:
        """The ``wp.Mesh`` of a trimesh (vertices in metres, world frame), built once per mesh object."""
        return self._mesh_arrays(mesh)[0]

    def _mesh_arrays(self, mesh: Any) -> tuple[wp.Mesh, wp.array, wp.array]:
        key = id(mesh)
        hit = self._meshes.get(key)
        if hit is not None and hit[0] is mesh:
            return hit[1], hit[2], hit[3]
        v = np.ascontiguousarray(mesh.vertices, dtype=np.float32)
        f = np.ascontiguousarray(mesh.faces, dtype=np.int32).reshape(-1)
        if len(v) == 0 or len(f) == 0:
            raise TnfError("warp_gel: the object mesh has no triangles")
        points = wp.array(v, dtype=wp.vec3, device=self.device)
        indices = wp.array(f, dtype=wp.int32, device=self.device)
        m = wp.Mesh(points=points, indices=indices)
        self._meshes = {key: (mesh, m, points, indices)}  # one object at a time: keep the newest only
        return m, points, indices

    def _buffer(self, part: int, name: str, shape: tuple[int, ...], dtype: Any) -> Any:
        key = f"{part}/{name}"  # each part of a batch split over threads has its own buffers
        buf = self._buffers.get(key)
        if buf is None or buf.shape != shape:
            buf = wp.empty(shape, dtype=dtype, device=self.device)
            self._buffers[key] = buf
        return buf

    # -- simulation ---------------------------------------------------------------------------------
    def press(
        self, mesh: Any, start_c2w: np.ndarray, force: float | np.ndarray, seed: int = 0, host: bool = True
    ) -> TouchBatch | None:
        """Press the sensor onto ``mesh`` from B start poses with a constant normal force.

        Args:
            mesh: the object (trimesh.Trimesh, metres, world frame).
            start_c2w: ``[B, 4, 4]`` sensor poses (camera-to-world, OpenGL: the sensor advances along its -z).
            force: target normal force, newtons (scalar or ``[B]``).
            seed: seed of the image noise.
            host: copy results to NumPy (``False`` leaves them on the device and returns None; for benchmarks).
        """
        self._last = time.perf_counter()
        c2w = np.asarray(start_c2w, dtype=np.float32).reshape(-1, 4, 4)
        meshes = self._mesh_arrays(mesh)
        return self._split(c2w, force, host, lambda c, f, part, b0: self._press(c, f, seed, host, part, b0, meshes))

    def press_heights(
        self,
        gaps: np.ndarray,
        force: float | np.ndarray | None = None,
        seed: int = 0,
        penetration: float | np.ndarray | None = None,
    ) -> TouchBatch:
        """Press the sensor with a constant normal force onto B surfaces given as height fields in its own
        pixel grid, instead of a mesh: steps 2-4 of ``press`` on a ray cast that was done elsewhere.
        With ``penetration`` instead of ``force``, each press goes that deep past first contact (metres,
        scalar or ``[B]``, at most the sensor's ``max_penetration``: deeper is a TnfError) and ``force`` reports
        the force it took.

        Args:
            gaps: ``[B, H, W]`` metres from each pixel's undeformed gel point (``Sensor.gel_points``) along the
                sensor's axis (-z) to the surface; non-finite where the pixel sees no surface. Only differences
                matter: a constant added to a touch's gaps changes nothing.
            force: target normal force, newtons (scalar or ``[B]``).
            seed: seed of the image noise.

        Returns:
            The touches as ``press`` returns them, with the sensor frame as the world frame: the start pose is
            the identity, and ``advance`` is the smallest gap.
        """
        s = self.sensor
        self._last = time.perf_counter()
        g = np.asarray(gaps, dtype=np.float32)
        if g.ndim != 3 or g.shape[1:] != (s.height, s.width):
            shape = f"[B, {s.height}, {s.width}]"
            raise TnfError(f"press_heights: gaps must be {shape} (the sensor's pixels), got {list(g.shape)}")
        if (force is None) == (penetration is None):
            raise TnfError("press_heights: give either force or penetration")
        c2w = np.broadcast_to(np.eye(4, dtype=np.float32), (len(g), 4, 4)).copy()
        if penetration is None:
            assert force is not None

            def run(c: np.ndarray, f: np.ndarray, part: int, b0: int) -> TouchBatch | None:
                return self._press(c, f, seed, True, part, b0, gaps=g[b0 : b0 + len(c)])

            out = self._split(c2w, force, True, run)
        else:
            d = np.broadcast_to(np.asarray(penetration, dtype=np.float64), (len(g),))
            if not (np.isfinite(d).all() and (d >= 0).all()):
                raise TnfError(f"press_heights: penetration must be finite and >= 0 metres, got {d.tolist()}")
            limit = s.cfg.max_penetration
            if (d > limit).any():
                i = int(np.argmax(d))
                raise TnfError(
                    f"press_heights: penetration {d[i] * 1e3:g} mm (touch {i}) is deeper than the sensor's "
                    f"max_penetration {limit * 1e3:g} mm (sensor.max_penetration)"
                )
            d = d.astype(np.float32)
            out = self._press(c2w, np.zeros(len(g), np.float32), seed, True, 0, 0, gaps=g, depths=d)
        assert out is not None
        return out

    def _split(self, c2w: np.ndarray, force: float | np.ndarray, host: bool, run: Any) -> TouchBatch | None:
        """``run(c2w, forces, part, b0)`` over the batch, split over ``cpu_threads`` threads on the CPU."""
        s = self.sensor
        batch = c2w.shape[0]
        check_memory(
            TOUCH_BYTES_PER_PIXEL * batch * s.width * s.height,
            f"a batch of {batch} touches",
            f"touch.batch_size={batch}, sensor.width={s.width}, sensor.height={s.height}",
        )
        forces = np.broadcast_to(np.asarray(force, dtype=np.float32), (batch,)).copy()
        for f in np.unique(forces):
            s.check_force(float(f))
        parts = min(batch, self.cfg.cpu_threads) if self.device.is_cpu else 1
        if parts <= 1:
            return run(c2w, forces, 0, 0)
        # Warp releases the GIL during a CPU launch: parts of the batch run concurrently, one thread each.
        from concurrent.futures import ThreadPoolExecutor

        bounds = np.linspace(0, batch, parts + 1).astype(int)
        with ThreadPoolExecutor(parts) as pool:
            jobs = [
                pool.submit(run, c2w[b0:b1], forces[b0:b1], i, int(b0))
                for i, (b0, b1) in enumerate(zip(bounds[:-1], bounds[1:]))
            ]
            outs = [j.result() for j in jobs]
        if not host:
            return None
        return TouchBatch(**{f: np.concatenate([getattr(o, f) for o in outs]) for f in TouchBatch.__dataclass_fields__})

    def _press(
        self,
        c2w: np.ndarray,
        forces: np.ndarray,
        seed: int,
        host: bool,
        part: int,
        b0: int,
        meshes: tuple | None = None,
        gaps: np.ndarray | None = None,
        depths: np.ndarray | None = None,
    ) -> TouchBatch | None:
        """Simulate touches ``b0 .. b0 + len(c2w)`` of a batch with the buffers of ``part``: ray cast against
        ``meshes`` (``_mesh_arrays``), or from the given ``gaps`` (``press_heights``; MISS where none)."""
        s = self.sensor
        batch = c2w.shape[0]
        hh, ww = s.height, s.width
        k = self.cfg.coarse_factor
        hc, wc = -(-hh // k), -(-ww // k)
        dev = self.device
        dx, dy = s.pixel_size()
        nb = self.cfg.histogram_bins
        bin_width = 0.5 * s.cfg.max_penetration / nb
        lam = self.falloff * s.cfg.thickness
        screen = (k * 0.5 * (dx + dy) / lam) ** 2

        span = self._span
        nblk, nblk_c = -(-ww // span), -(-wc // span)
        poses = wp.array(c2w, dtype=wp.mat44, device=dev)
        target = wp.array(forces, dtype=float, device=dev)
        t = self._buffer(part, "t", (batch, hh, ww), float)
        t_min = self._buffer(part, "t_min", (batch,), float)
        hist = self._buffer(part, "hist", (batch, nb), wp.int32)
        depth = self._buffer(part, "depth", (batch,), float)
        fout = self._buffer(part, "force", (batch,), float)
        cval = self._buffer(part, "cval", (batch, hc, wc), float)
        cmask = self._buffer(part, "cmask", (batch, hc, wc), wp.uint8)
        ra = self._buffer(part, "relax_a", (batch, hc, wc), float)
        rb = self._buffer(part, "relax_b", (batch, hc, wc), float)
        u = self._buffer(part, "u", (batch, hh, ww), float)
        contact = self._buffer(part, "contact", (batch, hh, ww), wp.uint8)
        diff = self._buffer(part, "diff", (batch, hh, ww), wp.vec3)
        image = self._buffer(part, "image", (batch, hh, ww, 3), wp.uint8)
        point = self._buffer(part, "point", (batch,), wp.vec3)
        t_min.fill_(MISS)
        hist.zero_()
        point.fill_(wp.vec3(float("nan")))

        if gaps is not None:
            given = self._buffer(part, "gaps", (batch, hh, ww), float)
            given.assign(gaps)
            wp.launch(_take_gaps, (batch, hh, ww), [given, self._gel, t, t_min], device=dev)
        else:
            assert meshes is not None
            self._cast(meshes, c2w, poses, t, t_min)
        self._phase(part, "ray cast")
        rows = (batch, hh, nblk)
        wp.launch(_gap_histogram, rows, [t, t_min, bin_width, poses, self._points, span, hist, point], device=dev)
        e_star = s.effective_modulus
        args = [hist, target, t_min, bin_width, dx * dy, e_star, s.cfg.thickness, depth, fout]
        if depths is None:
            wp.launch(_solve_force, batch, args, device=dev)
        else:
            args[1] = wp.array(depths, dtype=float, device=dev)
            wp.launch(_force_at_depth, batch, args, device=dev)
        self._phase(part, "force solve")
        coarse = (batch, hc, nblk_c)
        wp.launch(_coarse_constraint, coarse, [t, t_min, depth, k, span, cval, cmask, ra], device=dev)
        for _ in range(self.cfg.relax_iterations):
            wp.launch(_relax_step, coarse, [ra, cval, cmask, screen, span, rb], device=dev)
            ra, rb = rb, ra
        wp.launch(_compose, rows, [t, t_min, depth, ra, k, span, u, contact], device=dev)
        self._phase(part, "deformation")
        if self._table is not None:
            cal = self.calibration
            assert cal is not None
            args = [
                u,
                self._h0,
                self._gel,
                self._table,
                self._table_base,
                cal.max_slope,
                cal.slope_power,
                dx,
                dy,
                span,
                diff,
            ]
            wp.launch(_shade_table, rows, args, device=dev)
        elif s.custom_shading:
            diff = self._shade_on_host(u)
        else:
            c = s.cfg
            args = [u, self._h0, self._xy, self._gel, self._base, self._light_pos, self._light_rad]
            args += [c.camera_distance, dx, dy, c.ambient, c.diffuse, c.specular, c.shininess, self._int_shininess]
            args += [c.contrast, span, diff]
            wp.launch(_shade, rows, args, device=dev)
        self._phase(part, "shading")
        weights = self._no_blur
        if self._blur is not None:
            tmp = self._buffer(part, "diff_tmp", (batch, hh, ww), wp.vec3)
            wp.launch(_blur_rows, rows, [diff, self._blur, span, tmp], device=dev)
            diff, weights = tmp, self._blur
        args = [diff, weights, self._background, self._noise_table, float(self.noise_std), int(seed), b0, span, image]
        wp.launch(_blur_cols_finish, rows, args, device=dev)
        self._phase(part, "blur, noise")
        if not host:
            return None

        def host(a: wp.array) -> np.ndarray:
            # .numpy() of a CPU array is a view of the simulator's reused buffers: copy, so results outlive the
            # call. On a GPU it is already a new host array.
            return a.numpy().copy() if dev.is_cpu else a.numpy()

        tmin = host(t_min)
        hit = tmin < MISS
        pen = host(depth)
        axis = -c2w[:, :3, 2] / np.linalg.norm(c2w[:, :3, 2], axis=1, keepdims=True)
        contact_c2w = c2w.astype(np.float64).copy()
        shift = np.where(hit, tmin + pen, 0.0)
        contact_c2w[:, :3, 3] += axis * shift[:, None]
        images = host(image)
        ind = host(u)
        if s.decorates:
            images = s.decorate(images, ind)
        out = TouchBatch(
            images=images,
            indentation=ind,
            contact=host(contact).view(np.bool_),
            force=host(fout),
            penetration=pen,
            hit=hit,
            advance=np.where(hit, tmin, np.inf).astype(np.float32),
            contact_point=host(point),
            contact_c2w=contact_c2w,
        )
        self._phase(part, "host copy")
        return out

    def _cast(self, meshes: tuple, c2w: np.ndarray, poses: wp.array, t: wp.array, t_min: wp.array) -> None:
        """Step 1: the distance ``t`` from each gel pixel along the sensor's axis to the mesh, and its minimum."""
        dev = self.device
        batch = c2w.shape[0]
        hh, ww = self.sensor.height, self.sensor.width
        wmesh, verts, tris = meshes
        max_t = self.cfg.max_distance
        rot = c2w[:, :3, :3].astype(np.float64)
        rigid = np.allclose(rot.transpose(0, 2, 1) @ rot, np.eye(3), atol=1e-4) and np.allclose(
            c2w[:, 3], (0, 0, 0, 1), atol=1e-6
        )
        if rigid:
            # Rays are orthographic in the sensor frame: rasterise the mesh there (same hits as a ray cast).
            t.fill_(MISS)
            w2c = wp.array(np.linalg.inv(c2w.astype(np.float64)).astype(np.float32), dtype=wp.mat44, device=dev)
            ntri = tris.shape[0] // 3
            args = [verts, tris, w2c, self._points, self._gel, self._to_px, self._z_front, max_t, t, t_min]
            wp.launch(_rasterize, (batch, ntri), args, device=dev)
        else:
            args = [wmesh.id, poses, self._points, self._gel, max_t, t, t_min]
            wp.launch(_raycast, (batch, hh, ww), args, device=dev)

    def _shade_on_host(self, u: wp.array) -> wp.array:
        """Shading through an overridden ``Sensor.shade`` (NumPy, per touch)."""
        s = self.sensor
        h0 = self._h0.numpy()
        out = []
        for ind in u.numpy():
            h = h0 - ind
            lit = s.shade(s.gel_points(h), s.surface_normals(h))
            out.append(np.where(s.gel_mask()[..., None], s.cfg.contrast * (lit - self._base_np), 0.0))
        return wp.array(np.stack(out).astype(np.float32), dtype=wp.vec3, device=self.device)
