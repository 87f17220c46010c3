"""Rasterise a mesh into RGB-D with pyrender offscreen (EGL: Mesa on a CPU, the driver on a GPU).

One ``MeshRenderer`` keeps one OpenGL context, its compiled shaders and one pyrender scene for many views
and, through :meth:`MeshRenderer.set_mesh`, for many objects: between views only the camera node's pose and
intrinsics change. Lights are fixed in the world (not to the camera), so an object's shading is the same in
every view, as a scene representation fitted to the images expects.

Pixel convention: pixel ``(row i, column j)`` shows the scene at the pixel centre, image coordinates
``(j + 0.5, i + 0.5)`` with ``(0, 0)`` the top-left corner of the image, as in nerfstudio and in
:func:`tnf.cameras.camera_rays`: its ray's camera-space direction is ``((j + 0.5 - cx) / fx,
-(i + 0.5 - cy) / fy, -1)``. Depth is sampled there exactly (no multisampling of depth), so it agrees with
ray casting the mesh to float precision.
"""

from __future__ import annotations

from collections.abc import Sequence
from concurrent.futures import Executor, Future, wait
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from tnf.capture import intrinsics, write_frame, write_transforms
from tnf.env import headless_rendering

if TYPE_CHECKING:
    from tnf.capture import CaptureConfig

# Directions the world-fixed directional lights shine along (key, fill, rim), and their relative strengths.
_LIGHTS = (((-0.4, -0.5, -1.0), 1.0), ((0.8, 0.3, -0.2), 0.5), ((0.0, 0.9, 0.6), 0.35))


def _look_along(direction: Sequence[float]) -> np.ndarray:
    """A 4x4 pose whose -z axis points along ``direction`` (pyrender lights shine along their -z)."""
    d = np.asarray(direction, float)
    d = d / np.linalg.norm(d)
    up = np.array([0.0, 0.0, 1.0]) if abs(d[2]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(up, -d)
    x /= np.linalg.norm(x)
    y = np.cross(-d, x)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2] = x, y, -d
    return pose


def _offscreen_renderer(width: int, height: int, samples: int) -> Any:
    """A ``pyrender.OffscreenRenderer`` whose main framebuffer has ``samples`` samples per pixel.

    pyrender always allocates 4x multisampled colour and depth buffers. Multisampling quadruples the cost of
    llvmpipe (Mesa's CPU rasteriser), and resolving the depth buffer keeps one sample that is not at the
    pixel centre, so depth is off by up to ~1 mm at capture scale. ``samples=0`` gives plain buffers.
    """
    import pyrender
    from OpenGL.GL import GL_DEPTH_COMPONENT24, GL_RENDERBUFFER, GL_RGBA, glBindRenderbuffer
    from OpenGL.GL import glRenderbufferStorageMultisample as storage

    class _Renderer(pyrender.Renderer):
        def _configure_main_framebuffer(self) -> None:
            fresh = self._main_fb is None or self._main_fb_dims != (self.viewport_width, self.viewport_height)
            super()._configure_main_framebuffer()
            if fresh:  # re-specify the storage of the buffers pyrender just made with 4 samples
                for buf, fmt in ((self._main_cb_ms, GL_RGBA), (self._main_db_ms, GL_DEPTH_COMPONENT24)):
                    glBindRenderbuffer(GL_RENDERBUFFER, buf)
                    storage(GL_RENDERBUFFER, samples, fmt, self.viewport_width, self.viewport_height)

    off = pyrender.OffscreenRenderer(width, height)
    off._renderer = _Renderer(width, height)  # its buffers and shaders are created lazily on first render
    return off


def _release(off: Any) -> None:
    """Free an offscreen renderer's OpenGL objects and context without terminating the EGL display.

    pyrender's ``delete`` calls ``eglTerminate`` on the display, which every context in the process shares:
    it breaks all other live renderers. Leaving the display initialised costs nothing.
    """
    platform = off._platform
    if platform is None:
        return
    platform.make_current()
    off._renderer.delete()
    if getattr(platform, "_egl_context", None) is not None:
        from OpenGL.EGL import EGL_NO_CONTEXT, EGL_NO_SURFACE, eglDestroyContext, eglMakeCurrent

        eglMakeCurrent(platform._egl_display, EGL_NO_SURFACE, EGL_NO_SURFACE, EGL_NO_CONTEXT)
        eglDestroyContext(platform._egl_display, platform._egl_context)
        platform._egl_context = None
        platform._egl_display = None  # else the platform's __del__ terminates the display after all
    else:
        platform.delete_context()
    off._renderer = None
    off._platform = None


class MeshRenderer:
    """Render a ``trimesh.Trimesh`` from many cameras at ``width`` x ``height`` pixels.

    Args:
        mesh: the object, metres, with vertex colours or a texture (None: set one with :meth:`set_mesh`
            before rendering); :meth:`set_mesh` swaps it.
        width, height: image size in pixels.
        background: RGB in [0, 1] where no surface is hit.
        ambient: ambient light level in [0, 1].
        light_intensity: strength of the key directional light (W/m^2 in pyrender's units).
        antialias: multisample anti-aliasing samples of the colour image (0: one sample at each pixel centre,
            colour then agrees exactly with depth and with a ray per pixel; 4 or 8: smooth silhouettes, about
            3-4x slower on a CPU). Depth is always sampled at pixel centres.
    """

    def __init__(
        self,
        mesh: Any,
        width: int,
        height: int,
        background: Sequence[float] = (1.0, 1.0, 1.0),
        ambient: float = 0.35,
        light_intensity: float = 3.0,
        antialias: int = 0,
    ):
        headless_rendering()
        import pyrender

        if antialias < 0:
            raise ValueError(f"antialias must be >= 0 samples, got {antialias}")
        self.width, self.height = int(width), int(height)
        self.antialias = int(antialias)
        self.background = np.asarray(background, dtype=float)
        self._scene = pyrender.Scene(bg_color=[*self.background, 0.0], ambient_light=[ambient] * 3)
        for direction, strength in _LIGHTS:
            light = pyrender.DirectionalLight(color=np.ones(3), intensity=light_intensity * strength)
            self._scene.add(light, pose=_look_along(direction))
        self._camera = pyrender.IntrinsicsCamera(1.0, 1.0, 0.5, 0.5, znear=0.01, zfar=100.0)
        self._cam_node = self._scene.add(self._camera, pose=np.eye(4))
        self._mesh_node: Any = None
        self._radius = 0.0
        if mesh is not None:
            self.set_mesh(mesh)
        self._renderer: Any = _offscreen_renderer(self.width, self.height, self.antialias)

    def set_mesh(self, mesh: Any) -> None:
        """Render ``mesh`` (trimesh, metres) from now on; the context, shaders and lights are kept."""
        import pyrender

        if self._mesh_node is not None:
            self._scene.remove_node(self._mesh_node)  # its GPU buffers are freed at the next render
        self._mesh_node = self._scene.add(pyrender.Mesh.from_trimesh(mesh, smooth=False))
        # Near/far planes from the mesh size: tight planes keep depth precise.
        self._radius = float(np.linalg.norm(mesh.vertices, axis=1).max())

    def render(self, c2w: Any, intrinsics: Any) -> tuple[np.ndarray, np.ndarray]:
        """Render B views.

        Args:
            c2w: [B, 4, 4] or [4, 4] camera-to-world, OpenGL convention (camera looks along -z, +y up), metres.
            intrinsics: [4] or [B, 4] pinhole ``(fx, fy, cx, cy)`` in pixels, measured from the top-left corner
                of the image (pixel centres at +0.5, row 0 at the top).

        Returns:
            rgb: [B, H, W, 3] uint8, the background colour where empty.
            depth: [B, H, W] float32 z-depth in metres along the camera's -z axis, 0 where empty.
        """
        from pyrender import RenderFlags

        if self._renderer is None:
            raise RuntimeError("MeshRenderer.render after close()")
        if self._mesh_node is None:
            raise RuntimeError("MeshRenderer.render before set_mesh()")
        c2w = np.asarray(c2w, dtype=float)
        if c2w.ndim == 2:
            c2w = c2w[None]
        k = np.broadcast_to(np.asarray(intrinsics, dtype=float), (len(c2w), 4))
        rgbs = np.empty((len(c2w), self.height, self.width, 3), np.uint8)
        depths = np.empty((len(c2w), self.height, self.width), np.float32)
        # With multisampling on, a second pass with it off (pyrender turns it off for segmentation) gives
        # depth at the pixel centres; the flat segmentation shader makes that pass cheap.
        depth_pass = RenderFlags.SEG | RenderFlags.DEPTH_ONLY
        for i, (pose, (fx, fy, cx, cy)) in enumerate(zip(c2w, k)):
            dist = float(np.linalg.norm(pose[:3, 3]))
            self._camera.fx, self._camera.fy, self._camera.cx, self._camera.cy = fx, fy, cx, cy
            self._camera.znear = max(1e-3, 0.5 * (dist - self._radius))
            self._camera.zfar = dist + 2 * self._radius + 1e-2
            self._scene.set_pose(self._cam_node, pose)
            colour, depth = self._renderer.render(self._scene)
            if self.antialias:
                depth = self._renderer.render(self._scene, depth_pass, {self._mesh_node: 0})
            rgbs[i] = colour[..., :3]
            depths[i] = depth
        return rgbs, depths

    def close(self) -> None:
        """Free the OpenGL context (also done when the renderer is garbage-collected)."""
        r = getattr(self, "_renderer", None)
        if r is not None:
            self._renderer = None
            _release(r)

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:  # interpreter shutdown: the GL library may already be gone
            pass


def capture_object(
    renderer: MeshRenderer,
    folder: Path,
    train: np.ndarray,
    test: np.ndarray,
    cfg: CaptureConfig,
    pool: Executor,
    chunk: int = 8,
) -> float:
    """Render the current mesh from ``train`` and ``test`` poses [N, 4, 4] and write them into ``folder``.

    Writes the layout of :mod:`tnf.capture`. Views are rendered ``chunk`` at a time while ``pool``'s threads
    encode and write the previous ones (PNG and file writes release the GIL, llvmpipe leaves a core partly
    idle); returns when every file is written. Returns the mean fraction of training-image pixels the object
    covers.
    """

    (folder / "images").mkdir(parents=True, exist_ok=True)
    (folder / "depth").mkdir(parents=True, exist_ok=True)
    k = intrinsics(cfg)
    futures: list[Future[None]] = []
    coverage: list[np.ndarray] = []
    try:
        for split, poses in (("train", train), ("test", test)):
            if not len(poses):
                continue
            frames = write_transforms(folder, split, poses, cfg)["frames"]
            for start in range(0, len(poses), chunk):
                rgb, depth = renderer.render(poses[start : start + chunk], k)
                if split == "train":
                    coverage.append((depth > 0).mean(axis=(1, 2)))
                for frame, colour, z in zip(frames[start : start + chunk], rgb, depth):
                    futures.append(pool.submit(write_frame, folder, frame, colour, z))
    except BaseException:
        wait(futures)  # the caller removes the folder: let the writers finish first
        raise
    for f in futures:
        f.result()  # re-raises a write's error
    return float(np.concatenate(coverage).mean()) if coverage else 0.0
