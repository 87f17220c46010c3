"""Step 4 of ``warp_gel``: shading, blur and noise.

The deformed surface's normals lit by the sensor's coloured point lights (Phong: diffuse + specular, as
``Sensor.shade``; ``_shade``), or, for a calibrated sensor, its measured shading table read at the surface's slope
(``_shade_table``). The difference to the undeformed gel's shading is blurred and added to the background, with
Gaussian noise drawn from a table of normal quantiles (``_blur_rows``, ``_blur_cols_finish``).
"""

from __future__ import annotations

import numpy as np
import warp as wp

# Per-pixel kernels take ``span``: each thread handles ``span`` consecutive columns of one image row. On the CPU a
# warp launch runs its threads one after another, and a thread per row (span = W) avoids a per-thread cost that
# would otherwise exceed the work of the cheap kernels; on a GPU span = 1 (a thread per pixel, coalesced).
wp.set_module_options({"enable_backward": False})  # forward only: no gradients are taken; halves compile time

NOISE_TABLE = 4096  # entries of the inverse normal CDF used to draw image noise


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


def _normal_quantiles(n: int) -> np.ndarray:
    """``[n]`` float32 standard normal quantiles at probabilities ``(k + 0.5) / n``, rescaled to unit variance.

    Drawing a uniform index into this table gives Gaussian noise up to 1/n quantile resolution, at a fraction of
    the cost of a Box-Muller transform per value.
    """
    from statistics import NormalDist

    q = np.array([NormalDist().inv_cdf((k + 0.5) / n) for k in range(n)])
    return (q / np.sqrt(np.mean(q**2))).astype(np.float32)
