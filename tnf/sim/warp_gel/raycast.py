"""Step 1 of ``warp_gel``: the distance from each gel pixel along the sensor's axis (-z) to the object.

The rays are parallel, so for a rigid sensor pose the cast is an orthographic rasterisation of the mesh in the
sensor frame (``_rasterize``); scaled poses use ``wp.mesh_query_ray`` (``_raycast``); ``press_heights`` gives the
distances itself (``_take_gaps``). Each also keeps the smallest distance of a touch, where the sensor first
touches the object.
"""

from __future__ import annotations

import warp as wp

MISS = 1.0e9  # ray distance stored for pixels that see no object (and pixels outside the gel)

wp.set_module_options({"enable_backward": False})  # forward only: no gradients are taken; halves compile time


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
