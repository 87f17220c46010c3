"""``warp_gel``: a tactile simulator in NVIDIA Warp: a gel pressed with a constant force, shaded by the sensor's lights.

One call simulates a batch of touches of one object (a ``wp.Mesh`` built once per object) in a few kernel
launches, on the ``cpu`` or a ``cuda`` warp device with the same code:

1. **Height field.** From every pixel's point on the undeformed gel (``Sensor.gel_points``) a ray is cast along
   the sensor's axis (-z); ``t`` is the distance to the object. The sensor first touches the object after
   advancing ``t_min = min t``; the gap under each pixel is then ``g = t - t_min``.
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
   background, then Gaussian noise. With no contact the image is the background plus noise.

Outputs (``TouchBatch``): 8-bit RGB images, indentation maps (metres), contact masks, the achieved force (N),
the penetration ``d`` (m), the first-contact point and the sensor pose at contact.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import warp as wp

from tnf.errors import TnfError
from tnf.registry import SIMULATORS
from tnf.sensors.base import Sensor

MISS = 1.0e9  # ray distance stored for pixels that see no object (and pixels outside the gel)


# -- kernels ------------------------------------------------------------------------------------------
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
    hist: wp.array2d(dtype=wp.int32),
):
    b, r, c = wp.tid()
    g = t[b, r, c] - t_min[b]
    if t[b, r, c] < MISS:
        k = int(g / bin_width)
        if k < hist.shape[1]:
            wp.atomic_add(hist, b, k, wp.int32(1))


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
        area = (below + 0.5 * cnt) * pixel_area
        a = wp.sqrt(area / wp.pi)
        s = a / thickness
        df = 2.0 * e_star * a * (1.0 + 1.33 * s + 1.33 * s * s * s) * step
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
def _coarse_constraint(
    t: wp.array3d(dtype=float),
    t_min: wp.array(dtype=float),
    depth: wp.array(dtype=float),
    factor: int,
    cval: wp.array3d(dtype=float),
    cmask: wp.array3d(dtype=wp.uint8),
    relax: wp.array3d(dtype=float),
):
    b, i, j = wp.tid()
    d = depth[b]
    hit = wp.int32(0)
    total = wp.float32(0.0)
    count = wp.int32(0)
    for di in range(factor):
        for dj in range(factor):
            r = i * factor + di
            c = j * factor + dj
            if r < t.shape[1] and c < t.shape[2]:
                g = t[b, r, c] - t_min[b]
                if t[b, r, c] < MISS and d > 0.0 and g <= 0.5 * d:
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
    dst: wp.array3d(dtype=float),
):
    # Jacobi step of lap(u) = u / lambda^2 with u fixed in contact cells and u = 0 beyond the gel's rim.
    b, i, j = wp.tid()
    if cmask[b, i, j] != wp.uint8(0):
        dst[b, i, j] = cval[b, i, j]
        return
    h = src.shape[1]
    w = src.shape[2]
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


@wp.kernel
def _compose(
    t: wp.array3d(dtype=float),
    t_min: wp.array(dtype=float),
    depth: wp.array(dtype=float),
    relax: wp.array3d(dtype=float),
    factor: int,
    u_out: wp.array3d(dtype=float),
    contact: wp.array3d(dtype=wp.uint8),
):
    b, r, c = wp.tid()
    d = depth[b]
    tv = t[b, r, c]
    g = tv - t_min[b]
    inter = d - g  # how far the object reaches past the undeformed gel
    if tv >= MISS:
        inter = -1.0
    in_contact = d > 0.0 and tv < MISS and g <= 0.5 * d
    # Smooth fall-off: cubic B-spline of the coarse relaxed field (cell centres at (k + 0.5) * factor - 0.5).
    fk = float(factor)
    gr = (float(r) + 0.5) / fk - 0.5
    gc = (float(c) + 0.5) / fk - 0.5
    i0 = int(wp.floor(gr))
    j0 = int(wp.floor(gc))
    fr = gr - float(i0)
    fc = gc - float(j0)
    hc = relax.shape[1]
    wc = relax.shape[2]
    acc = wp.float32(0.0)
    for ki in range(4):
        ii = wp.clamp(i0 - 1 + ki, 0, hc - 1)
        wi = _bspline(fr, ki)
        for kj in range(4):
            jj = wp.clamp(j0 - 1 + kj, 0, wc - 1)
            acc += wi * _bspline(fc, kj) * relax[b, ii, jj]
    # Inside the contact the smoothed field lies below the object (smoothing lowers peaks), so the max takes
    # the object's shape there and blends into the fall-off at the contact's edge without a kink.
    u = wp.max(wp.max(acc, 0.0), inter)
    if d <= 0.0:
        u = 0.0
    u_out[b, r, c] = u
    contact[b, r, c] = wp.uint8(1) if in_contact else wp.uint8(0)


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
    contrast: float,
    diff: wp.array3d(dtype=wp.vec3),
):
    b, r, c = wp.tid()
    if gel[r, c] == wp.uint8(0):
        diff[b, r, c] = wp.vec3(0.0)
        return
    hh = u.shape[1]
    ww = u.shape[2]
    # Outward height of the deformed gel; the surface is z = -(cam_dist + height).
    rm = wp.max(r - 1, 0)
    rp = wp.min(r + 1, hh - 1)
    cm = wp.max(c - 1, 0)
    cp = wp.min(c + 1, ww - 1)
    hcp = h0[r, cp] - u[b, r, cp]
    hcm = h0[r, cm] - u[b, r, cm]
    hrp = h0[rp, c] - u[b, rp, c]
    hrm = h0[rm, c] - u[b, rm, c]
    dzdx = -(hcp - hcm) / (float(cp - cm) * dx)
    dzdy = (hrp - hrm) / (float(rp - rm) * dy)  # rows grow toward -y
    n = wp.normalize(wp.vec3(-dzdx, -dzdy, 1.0))
    p2 = xy[r, c]
    p = wp.vec3(p2[0], p2[1], -(cam_dist + h0[r, c] - u[b, r, c]))
    view = wp.normalize(-p)
    col = wp.vec3(ambient, ambient, ambient)
    for k in range(light_pos.shape[0]):
        ldir = wp.normalize(light_pos[k] - p)
        ndl = wp.max(wp.dot(n, ldir), 0.0)
        half = wp.normalize(ldir + view)
        ndh = wp.max(wp.dot(n, half), 0.0)
        col += light_rad[k] * (diffuse * ndl + specular * wp.pow(ndh, shininess))
    diff[b, r, c] = contrast * (col - base[r, c])


@wp.kernel
def _blur_rows(src: wp.array3d(dtype=wp.vec3), weights: wp.array(dtype=float), dst: wp.array3d(dtype=wp.vec3)):
    b, r, c = wp.tid()
    rad = (weights.shape[0] - 1) // 2
    acc = wp.vec3(0.0)
    for k in range(weights.shape[0]):
        cc = wp.clamp(c + k - rad, 0, src.shape[2] - 1)
        acc += weights[k] * src[b, r, cc]
    dst[b, r, c] = acc


@wp.kernel
def _blur_cols(src: wp.array3d(dtype=wp.vec3), weights: wp.array(dtype=float), dst: wp.array3d(dtype=wp.vec3)):
    b, r, c = wp.tid()
    rad = (weights.shape[0] - 1) // 2
    acc = wp.vec3(0.0)
    for k in range(weights.shape[0]):
        rr = wp.clamp(r + k - rad, 0, src.shape[1] - 1)
        acc += weights[k] * src[b, rr, c]
    dst[b, r, c] = acc


@wp.kernel
def _finish(
    diff: wp.array3d(dtype=wp.vec3),
    background: wp.array2d(dtype=wp.vec3),
    noise_std: float,
    seed: int,
    image: wp.array4d(dtype=wp.uint8),
):
    b, r, c = wp.tid()
    v = background[r, c] + diff[b, r, c]
    if noise_std > 0.0:
        state = wp.rand_init(seed, (b * diff.shape[1] + r) * diff.shape[2] + c)
        v = v + noise_std * wp.vec3(wp.randn(state), wp.randn(state), wp.randn(state))
    for k in range(3):
        image[b, r, c, k] = wp.uint8(int(wp.clamp(v[k] + 0.5, 0.0, 255.0)))


@wp.kernel
def _contact_point(
    t: wp.array3d(dtype=float),
    t_min: wp.array(dtype=float),
    c2w: wp.array(dtype=wp.mat44),
    points: wp.array2d(dtype=wp.vec3),
    out: wp.array(dtype=wp.vec3),
):
    b, r, c = wp.tid()
    if t[b, r, c] == t_min[b] and t[b, r, c] < MISS:
        m = c2w[b]
        o = wp.transform_point(m, points[r, c])
        d = wp.normalize(wp.transform_vector(m, wp.vec3(0.0, 0.0, -1.0)))
        out[b] = o + d * t[b, r, c]


# -- the simulator ------------------------------------------------------------------------------------
@dataclass
class TouchBatch:
    """Results of B touches of one object; arrays are NumPy on the host.

    Attributes:
        images: ``[B, H, W, 3]`` uint8 tactile images.
        indentation: ``[B, H, W]`` float32, metres the gel surface moved toward the camera.
        contact: ``[B, H, W]`` bool, pixels where the gel touches the object.
        force: ``[B]`` float32 normal force reached, newtons (the target unless the press hit ``max_penetration``).
        penetration: ``[B]`` float32 metres the sensor advanced past first contact.
        hit: ``[B]`` bool, whether the gel touched the object at all (no hit: image = background + noise).
        advance: ``[B]`` float32 metres from the start pose to first contact (inf without a hit).
        contact_point: ``[B, 3]`` world position of the first contact (NaN without a hit).
        contact_c2w: ``[B, 4, 4]`` sensor pose (camera-to-world) while pressing.
    """

    images: np.ndarray
    indentation: np.ndarray
    contact: np.ndarray
    force: np.ndarray
    penetration: np.ndarray
    hit: np.ndarray
    advance: np.ndarray
    contact_point: np.ndarray
    contact_c2w: np.ndarray


@SIMULATORS.register("warp_gel")
class WarpGel:
    """Elastic gel pressed with a constant force, ray cast and shaded in NVIDIA Warp (CPU or CUDA)."""

    @dataclass
    class Config:
        histogram_bins: int = 512
        """Resolution of the gap histogram that tabulates force against penetration (bins over max_penetration)."""
        coarse_factor: int = 4
        """Downsampling of the grid on which the fall-off around the contact is relaxed (pixels per cell)."""
        relax_iterations: int = 60
        """Jacobi iterations of the fall-off relaxation."""
        falloff: float = 0.5
        """Decay length of the gel's deformation around the contact, as a multiple of the gel thickness."""
        max_distance: float = 2.0
        """Longest ray cast from the gel toward the object, metres."""

        def validate(self) -> None:
            if self.histogram_bins < 8:
                raise ValueError(f"histogram_bins must be >= 8, got {self.histogram_bins}")
            if self.coarse_factor < 1:
                raise ValueError(f"coarse_factor must be >= 1, got {self.coarse_factor}")
            if self.relax_iterations < 0:
                raise ValueError(f"relax_iterations must be >= 0, got {self.relax_iterations}")
            if self.falloff <= 0 or self.max_distance <= 0:
                raise ValueError("falloff and max_distance must be > 0")

    def __init__(self, cfg: Config, sensor: Sensor, device: str = "cpu"):
        """``sensor``: the tactile sensor to simulate; ``device``: warp device (``cpu``, ``cuda:0``)."""
        self.cfg = cfg
        self.sensor = sensor
        wp.init()
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
        sigma = s.cfg.blur_sigma
        if sigma > 0:
            radius = max(1, int(math.ceil(3 * sigma)))
            k = np.exp(-0.5 * (np.arange(-radius, radius + 1) / sigma) ** 2)
            self._blur = wp.array((k / k.sum()).astype(np.float32), dtype=float, device=dev)
        else:
            self._blur = None
        self._meshes: dict[int, tuple[Any, wp.Mesh]] = {}
        self._buffers: dict[str, Any] = {}

    # -- meshes -------------------------------------------------------------------------------------
    def mesh(self, mesh: Any) -> wp.Mesh:
        """The ``wp.Mesh`` of a trimesh (vertices in metres, world frame), built once per mesh object."""
        key = id(mesh)
        hit = self._meshes.get(key)
        if hit is not None and hit[0] is mesh:
            return hit[1]
        v = np.ascontiguousarray(mesh.vertices, dtype=np.float32)
        f = np.ascontiguousarray(mesh.faces, dtype=np.int32).reshape(-1)
        if len(v) == 0 or len(f) == 0:
            raise TnfError("warp_gel: the object mesh has no triangles")
        m = wp.Mesh(
            points=wp.array(v, dtype=wp.vec3, device=self.device),
            indices=wp.array(f, dtype=wp.int32, device=self.device),
        )
        self._meshes = {key: (mesh, m)}  # one object at a time: keep the newest only
        return m

    def _buffer(self, name: str, shape: tuple[int, ...], dtype: Any) -> Any:
        buf = self._buffers.get(name)
        if buf is None or buf.shape != shape:
            buf = wp.empty(shape, dtype=dtype, device=self.device)
            self._buffers[name] = buf
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
        s = self.sensor
        c2w = np.asarray(start_c2w, dtype=np.float32).reshape(-1, 4, 4)
        batch = c2w.shape[0]
        forces = np.broadcast_to(np.asarray(force, dtype=np.float32), (batch,)).copy()
        for f in np.unique(forces):
            s.check_force(float(f))
        hh, ww = s.height, s.width
        k = self.cfg.coarse_factor
        hc, wc = -(-hh // k), -(-ww // k)
        dev = self.device
        wmesh = self.mesh(mesh)
        dx, dy = s.pixel_size()
        nb = self.cfg.histogram_bins
        bin_width = 0.5 * s.cfg.max_penetration / nb
        lam = self.cfg.falloff * s.cfg.thickness
        screen = (k * 0.5 * (dx + dy) / lam) ** 2

        poses = wp.array(c2w, dtype=wp.mat44, device=dev)
        target = wp.array(forces, dtype=float, device=dev)
        t = self._buffer("t", (batch, hh, ww), float)
        t_min = wp.full(batch, MISS, dtype=float, device=dev)
        hist = wp.zeros((batch, nb), dtype=wp.int32, device=dev)
        depth = self._buffer("depth", (batch,), float)
        fout = self._buffer("force", (batch,), float)
        cval = self._buffer("cval", (batch, hc, wc), float)
        cmask = self._buffer("cmask", (batch, hc, wc), wp.uint8)
        ra = self._buffer("relax_a", (batch, hc, wc), float)
        rb = self._buffer("relax_b", (batch, hc, wc), float)
        u = self._buffer("u", (batch, hh, ww), float)
        contact = self._buffer("contact", (batch, hh, ww), wp.uint8)
        diff = self._buffer("diff", (batch, hh, ww), wp.vec3)
        image = self._buffer("image", (batch, hh, ww, 3), wp.uint8)
        point = wp.full(batch, wp.vec3(float("nan")), dtype=wp.vec3, device=dev)

        dims = (batch, hh, ww)
        wp.launch(
            _raycast, dims, [wmesh.id, poses, self._points, self._gel, self.cfg.max_distance, t, t_min], device=dev
        )
        wp.launch(_gap_histogram, dims, [t, t_min, bin_width, hist], device=dev)
        e_star = s.effective_modulus
        args = [hist, target, t_min, bin_width, dx * dy, e_star, s.cfg.thickness, depth, fout]
        wp.launch(_solve_force, batch, args, device=dev)
        wp.launch(_coarse_constraint, (batch, hc, wc), [t, t_min, depth, k, cval, cmask, ra], device=dev)
        for _ in range(self.cfg.relax_iterations):
            wp.launch(_relax_step, (batch, hc, wc), [ra, cval, cmask, screen, rb], device=dev)
            ra, rb = rb, ra
        wp.launch(_compose, dims, [t, t_min, depth, ra, k, u, contact], device=dev)
        if s.custom_shading:
            diff = self._shade_on_host(u)
        else:
            c = s.cfg
            args = [u, self._h0, self._xy, self._gel, self._base, self._light_pos, self._light_rad]
            args += [c.camera_distance, dx, dy, c.ambient, c.diffuse, c.specular, c.shininess, c.contrast, diff]
            wp.launch(_shade, dims, args, device=dev)
        if self._blur is not None:
            tmp = self._buffer("diff_tmp", (batch, hh, ww), wp.vec3)
            wp.launch(_blur_rows, dims, [diff, self._blur, tmp], device=dev)
            wp.launch(_blur_cols, dims, [tmp, self._blur, diff], device=dev)
        wp.launch(_finish, dims, [diff, self._background, float(s.cfg.noise_std), int(seed), image], device=dev)
        wp.launch(_contact_point, dims, [t, t_min, poses, self._points, point], device=dev)
        if not host:
            return None

        tmin = t_min.numpy()
        hit = tmin < MISS
        pen = depth.numpy()
        axis = -c2w[:, :3, 2] / np.linalg.norm(c2w[:, :3, 2], axis=1, keepdims=True)
        contact_c2w = c2w.astype(np.float64).copy()
        shift = np.where(hit, tmin + pen, 0.0)
        contact_c2w[:, :3, 3] += axis * shift[:, None]
        images = image.numpy()
        ind = u.numpy()
        if s.decorates:
            images = s.decorate(images, ind)
        return TouchBatch(
            images=images,
            indentation=ind,
            contact=contact.numpy().astype(bool),
            force=fout.numpy(),
            penetration=pen,
            hit=hit,
            advance=np.where(hit, tmin, np.inf).astype(np.float32),
            contact_point=point.numpy(),
            contact_c2w=contact_c2w,
        )

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
