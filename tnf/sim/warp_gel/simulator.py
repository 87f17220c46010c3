"""The ``warp_gel`` simulator: ``WarpGel`` holds a sensor's gel on a warp device and launches the kernels of each
step of a press (``raycast``, ``contact``, ``deformation``, ``shading``) on batches of touches."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import warp as wp

from tnf.errors import TnfError
from tnf.registry import FROM_YAML, yaml_defaults, yaml_field
from tnf.runtime import check_memory, init_warp
from tnf.sensors.base import Sensor
from tnf.sim.base import Simulator, TouchBatch
from tnf.sim.warp_gel.contact import _force_at_depth, _gap_histogram, _solve_force
from tnf.sim.warp_gel.deformation import _coarse_constraint, _compose, _relax_step
from tnf.sim.warp_gel.raycast import MISS, _rasterize, _raycast, _take_gaps
from tnf.sim.warp_gel.shading import NOISE_TABLE, _blur_cols_finish, _blur_rows, _normal_quantiles, _shade, _shade_table

SENSOR_BYTES_PER_PIXEL = 400
"""Host memory per image pixel of what a simulator holds and builds once (the gel's grids, shading, background),
a generous estimate."""
TOUCH_BYTES_PER_PIXEL = 80
"""Memory per image pixel of one touch of a batch (device buffers and the host copies of the results)."""


@dataclass
class _PressBuffers:
    """One part's device arrays for a batch of touches, and the launch shapes of the per-pixel kernels."""

    rows: tuple[int, int, int]
    """``(B, H, column blocks)``: one thread per ``span`` columns of an image row."""
    coarse: tuple[int, int, int]
    """``(B, coarse rows, coarse column blocks)``, for the fall-off's grid."""
    t: wp.array
    t_min: wp.array
    hist: wp.array
    depth: wp.array
    force: wp.array
    cval: wp.array
    cmask: wp.array
    relax_a: wp.array
    relax_b: wp.array
    u: wp.array
    contact: wp.array
    diff: wp.array
    diff_tmp: wp.array | None
    """Where the blur's first pass goes; None for a sensor without blur."""
    image: wp.array
    point: wp.array


class WarpGel(Simulator):
    """Elastic gel pressed with a constant force, ray cast and shaded in NVIDIA Warp (CPU or CUDA)."""

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
        cpu_threads: int = yaml_field(identity=False)
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
        buf = self._press_buffers(part, c2w.shape[0])
        poses = wp.array(c2w, dtype=wp.mat44, device=self.device)
        if gaps is not None:
            given = self._buffer(part, "gaps", buf.t.shape, float)
            given.assign(gaps)
            wp.launch(_take_gaps, buf.t.shape, [given, self._gel, buf.t, buf.t_min], device=self.device)
        else:
            assert meshes is not None
            self._cast(meshes, c2w, poses, buf.t, buf.t_min)
        self._phase(part, "ray cast")
        self._solve(buf, poses, forces, depths)
        self._phase(part, "force solve")
        self._deform(buf)
        self._phase(part, "deformation")
        diff = self._shading(buf)
        self._phase(part, "shading")
        self._finish(part, buf, diff, seed, b0)
        self._phase(part, "blur, noise")
        if not host:
            return None
        out = self._results(c2w, buf)
        self._phase(part, "host copy")
        return out

    def _press_buffers(self, part: int, batch: int) -> _PressBuffers:
        """The device buffers of ``part`` for ``batch`` touches, reset where a press accumulates into them."""
        s = self.sensor
        hh, ww = s.height, s.width
        k = self.cfg.coarse_factor
        hc, wc = -(-hh // k), -(-ww // k)
        span = self._span
        buf = _PressBuffers(
            rows=(batch, hh, -(-ww // span)),
            coarse=(batch, hc, -(-wc // span)),
            t=self._buffer(part, "t", (batch, hh, ww), float),
            t_min=self._buffer(part, "t_min", (batch,), float),
            hist=self._buffer(part, "hist", (batch, self.cfg.histogram_bins), wp.int32),
            depth=self._buffer(part, "depth", (batch,), float),
            force=self._buffer(part, "force", (batch,), float),
            cval=self._buffer(part, "cval", (batch, hc, wc), float),
            cmask=self._buffer(part, "cmask", (batch, hc, wc), wp.uint8),
            relax_a=self._buffer(part, "relax_a", (batch, hc, wc), float),
            relax_b=self._buffer(part, "relax_b", (batch, hc, wc), float),
            u=self._buffer(part, "u", (batch, hh, ww), float),
            contact=self._buffer(part, "contact", (batch, hh, ww), wp.uint8),
            diff=self._buffer(part, "diff", (batch, hh, ww), wp.vec3),
            diff_tmp=self._buffer(part, "diff_tmp", (batch, hh, ww), wp.vec3) if self._blur is not None else None,
            image=self._buffer(part, "image", (batch, hh, ww, 3), wp.uint8),
            point=self._buffer(part, "point", (batch,), wp.vec3),
        )
        buf.t_min.fill_(MISS)
        buf.hist.zero_()
        buf.point.fill_(wp.vec3(float("nan")))
        return buf

    def _solve(self, buf: _PressBuffers, poses: wp.array, forces: np.ndarray, depths: np.ndarray | None) -> None:
        """Step 2: the gap histogram and first contact point, then the penetration that reaches the target
        ``forces``, or, where ``depths`` are given, the force at those penetrations."""
        s, dev = self.sensor, self.device
        dx, dy = s.pixel_size()
        bin_width = 0.5 * s.cfg.max_penetration / self.cfg.histogram_bins
        args = [buf.t, buf.t_min, bin_width, poses, self._points, self._span, buf.hist, buf.point]
        wp.launch(_gap_histogram, buf.rows, args, device=dev)
        kernel, goal = (_solve_force, forces) if depths is None else (_force_at_depth, depths)
        args = [buf.hist, wp.array(goal, dtype=float, device=dev), buf.t_min, bin_width, dx * dy]
        args += [s.effective_modulus, s.cfg.thickness, buf.depth, buf.force]
        wp.launch(kernel, buf.rows[0], args, device=dev)

    def _deform(self, buf: _PressBuffers) -> None:
        """Step 3: the indentation ``buf.u`` and contact mask: the contact's shape, relaxed fall-off around it."""
        s, dev = self.sensor, self.device
        dx, dy = s.pixel_size()
        k = self.cfg.coarse_factor
        lam = self.falloff * s.cfg.thickness
        screen = (k * 0.5 * (dx + dy) / lam) ** 2
        span = self._span
        ra, rb = buf.relax_a, buf.relax_b
        args = [buf.t, buf.t_min, buf.depth, k, span, buf.cval, buf.cmask, ra]
        wp.launch(_coarse_constraint, buf.coarse, args, device=dev)
        for _ in range(self.cfg.relax_iterations):
            wp.launch(_relax_step, buf.coarse, [ra, buf.cval, buf.cmask, screen, span, rb], device=dev)
            ra, rb = rb, ra
        wp.launch(_compose, buf.rows, [buf.t, buf.t_min, buf.depth, ra, k, span, buf.u, buf.contact], device=dev)

    def _shading(self, buf: _PressBuffers) -> wp.array:
        """Step 4: the change of each pixel's colour from the undeformed gel's (before blur), ``[B, H, W]`` vec3."""
        s, dev = self.sensor, self.device
        dx, dy = s.pixel_size()
        span, u, diff = self._span, buf.u, buf.diff
        if self._table is not None:
            cal = self.calibration
            assert cal is not None
            args = [u, self._h0, self._gel, self._table, self._table_base, cal.max_slope, cal.slope_power]
            args += [dx, dy, span, diff]
            wp.launch(_shade_table, buf.rows, args, device=dev)
        elif s.custom_shading:
            diff = self._shade_on_host(u)
        else:
            c = s.cfg
            args = [u, self._h0, self._xy, self._gel, self._base, self._light_pos, self._light_rad]
            args += [c.camera_distance, dx, dy, c.ambient, c.diffuse, c.specular, c.shininess, self._int_shininess]
            args += [c.contrast, span, diff]
            wp.launch(_shade, buf.rows, args, device=dev)
        return diff

    def _finish(self, part: int, buf: _PressBuffers, diff: wp.array, seed: int, b0: int) -> None:
        """The 8-bit images ``buf.image``: ``diff`` blurred, added to the background, with noise."""
        dev = self.device
        weights = self._no_blur
        if self._blur is not None:
            assert buf.diff_tmp is not None
            wp.launch(_blur_rows, buf.rows, [diff, self._blur, self._span, buf.diff_tmp], device=dev)
            diff, weights = buf.diff_tmp, self._blur
        args = [diff, weights, self._background, self._noise_table, float(self.noise_std), int(seed), b0]
        wp.launch(_blur_cols_finish, buf.rows, [*args, self._span, buf.image], device=dev)

    def _results(self, c2w: np.ndarray, buf: _PressBuffers) -> TouchBatch:
        """The touches on the host, with the sensor poses at contact."""
        s, dev = self.sensor, self.device

        def host(a: wp.array) -> np.ndarray:
            # .numpy() of a CPU array is a view of the simulator's reused buffers: copy, so results outlive the
            # call. On a GPU it is already a new host array.
            return a.numpy().copy() if dev.is_cpu else a.numpy()

        tmin = host(buf.t_min)
        hit = tmin < MISS
        pen = host(buf.depth)
        axis = -c2w[:, :3, 2] / np.linalg.norm(c2w[:, :3, 2], axis=1, keepdims=True)
        contact_c2w = c2w.astype(np.float64).copy()
        shift = np.where(hit, tmin + pen, 0.0)
        contact_c2w[:, :3, 3] += axis * shift[:, None]
        images = host(buf.image)
        ind = host(buf.u)
        if s.decorates:
            images = s.decorate(images, ind)
        return TouchBatch(
            images=images,
            indentation=ind,
            contact=host(buf.contact).view(np.bool_),
            force=host(buf.force),
            penetration=pen,
            hit=hit,
            advance=np.where(hit, tmin, np.inf).astype(np.float32),
            contact_point=host(buf.point),
            contact_c2w=contact_c2w,
        )

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
