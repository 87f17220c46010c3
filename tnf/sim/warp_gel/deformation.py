"""Step 3 of ``warp_gel``: the gel's deformation.

Where in contact the gel takes the object's shape (indentation ``u = d - g``). Around the contact the surface
falls off smoothly: a screened membrane equation ``lap(u) = u / lambda^2`` relaxed on a coarse grid with the
contact as a constraint (``_coarse_constraint``, ``_relax_step``), upsampled with cubic B-splines (``_compose``).
"""

from __future__ import annotations

import warp as wp

from tnf.sim.warp_gel.raycast import MISS

# Per-pixel kernels take ``span``: each thread handles ``span`` consecutive columns of one image row. On the CPU a
# warp launch runs its threads one after another, and a thread per row (span = W) avoids a per-thread cost that
# would otherwise exceed the work of the cheap kernels; on a GPU span = 1 (a thread per pixel, coalesced).
wp.set_module_options({"enable_backward": False})  # forward only: no gradients are taken; halves compile time


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
