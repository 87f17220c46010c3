"""Step 2 of ``warp_gel``: the constant-force press, by the method of dimensionality reduction.

After advancing ``d`` past first contact, the contact area is where the gap ``g <= d / 2``; the normal force
integrates the incremental stiffness ``dF/dd = 2 E* a`` (``a = sqrt(A / pi)``), stiffened for a thin bonded layer.
``F(d)`` is tabulated from a histogram of gaps (``_gap_histogram``) and inverted for a target force
(``_solve_force``), or read at a given depth (``_force_at_depth``).
"""

from __future__ import annotations

import warp as wp

from tnf.sim.warp_gel.raycast import MISS

UNBOUNDED = 1.0e30  # a depth or force limit that is never reached

# Per-pixel kernels take ``span``: each thread handles ``span`` consecutive columns of one image row. On the CPU a
# warp launch runs its threads one after another, and a thread per row (span = W) avoids a per-thread cost that
# would otherwise exceed the work of the cheap kernels; on a GPU span = 1 (a thread per pixel, coalesced).
wp.set_module_options({"enable_backward": False})  # forward only: no gradients are taken; halves compile time


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


@wp.func
def _force_integral(
    hist: wp.array2d(dtype=wp.int32),
    b: int,
    step: float,
    pixel_area: float,
    e_star: float,
    thickness: float,
    max_depth: float,
    max_force: float,
) -> wp.vec2:
    # (penetration, force) of touch b: integrate dF/dd = 2 E* a f(a/h) over d in steps of ``step`` (the contact
    # area at penetration d is the area with gap <= d / 2, gaps binned at step / 2) until the depth reaches
    # ``max_depth`` or the force ``max_force``, whichever comes first. Past the histogram's last bin the press
    # stops at its deepest, ``n * step``.
    n = hist.shape[1]
    f = wp.float32(0.0)
    below = wp.float32(0.0)  # pixels in bins before the current one
    for k in range(n):
        lo = float(k) * step
        if lo >= max_depth:
            break
        cnt = float(hist[b, k])
        df = _stiffness((below + 0.5 * cnt) * pixel_area, e_star, thickness) * wp.min(max_depth - lo, step)
        if f + df >= max_force and df > 0.0:
            frac = (max_force - f) / df
            return wp.vec2((float(k) + frac) * step, max_force)
        f += df
        below += cnt
    return wp.vec2(wp.min(max_depth, float(n) * step), f)


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
    # One thread per touch: the penetration at which the force reaches the target (the deepest the histogram
    # covers, and the force there, when the target is out of reach).
    b = wp.tid()
    depth[b] = 0.0
    force[b] = 0.0
    if t_min[b] >= MISS:
        return
    df = _force_integral(hist, b, 2.0 * bin_width, pixel_area, e_star, thickness, UNBOUNDED, target[b])
    depth[b] = df[0]
    force[b] = df[1]


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
    d = wp.clamp(target_depth[b], 0.0, float(hist.shape[1]) * step)
    df = _force_integral(hist, b, step, pixel_area, e_star, thickness, d, UNBOUNDED)
    depth[b] = df[0]
    force[b] = df[1]
