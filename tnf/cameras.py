"""Pinhole cameras: poses, rays, and the ``transforms.json`` files that hold them.

Conventions: a camera pose is a camera-to-world 4x4 matrix in the OpenGL convention (the camera looks along
its -z axis, +y up, image rows go down), metres; world +z is the object's up. Intrinsics are
``(fx, fy, cx, cy)`` in pixels and rays go through pixel centres. Camera files are in the instant-ngp /
nerfstudio ``transforms.json`` format (``tnf.capture`` writes them).
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from tnf.errors import TnfError

if TYPE_CHECKING:
    import torch


def look_at(
    eye: Any,
    target: Any = (0.0, 0.0, 0.0),
    up: Any = (0.0, 0.0, 1.0),
    fallback: Literal["cone", "parallel"] = "cone",
) -> np.ndarray:
    """Camera-to-world 4x4 float64 (OpenGL: looks along -z, +y up) at ``eye`` looking at ``target``, metres.

    ``up`` fixes the roll. ``fallback`` says what replaces it when the view is close to it:

    - ``cone``: world +y, when the view lies within 2.6 degrees of ``up`` (``|cos| > 0.999``);
    - ``parallel``: world +y, else world +x, when the view is parallel to ``up`` (``|view x up| <= 1e-3``).
    """
    eye = np.asarray(eye, dtype=np.float64)
    back = eye - np.asarray(target, dtype=np.float64)
    back /= np.linalg.norm(back)
    up = np.asarray(up, dtype=np.float64)
    if fallback == "cone":
        if abs(float(np.dot(back, up / np.linalg.norm(up)))) > 0.999:
            up = np.array([0.0, 1.0, 0.0])
        right = np.cross(up, back)
    elif fallback == "parallel":
        for cand in (up, np.array([0.0, 1.0, 0.0]), np.array([1.0, 0.0, 0.0])):
            right = np.cross(cand, back)
            if np.linalg.norm(right) > 1e-3:
                break
    else:
        raise TnfError(f"look_at fallback must be 'cone' or 'parallel', got {fallback!r}")
    right /= np.linalg.norm(right)
    true_up = np.cross(back, right)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, true_up, back, eye
    return c2w


def camera_rays(
    c2w: torch.Tensor, intrinsics: torch.Tensor, width: int, height: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Rays through the pixel centres of B pinhole cameras.

    Args:
        c2w: [B, 4, 4] camera-to-world (OpenGL: looks along -z, +y up), metres.
        intrinsics: [B, 4] or [4], ``(fx, fy, cx, cy)`` in pixels.
    Returns:
        origins [B, H, W, 3] (metres), unit directions [B, H, W, 3], and z_scale [B, H, W]: the cosine
        between each ray and the optical axis, so that ``z_depth = distance * z_scale``.
    """
    import torch

    c2w = c2w.reshape(-1, 4, 4).float()
    B = c2w.shape[0]
    intr = intrinsics.to(c2w).reshape(-1, 4).expand(B, 4)
    dev = c2w.device
    v, u = torch.meshgrid(
        torch.arange(height, device=dev, dtype=torch.float32) + 0.5,
        torch.arange(width, device=dev, dtype=torch.float32) + 0.5,
        indexing="ij",
    )
    fx, fy, cx, cy = (intr[:, i].view(B, 1, 1) for i in range(4))
    x = (u - cx) / fx
    y = -(v - cy) / fy  # image rows go down, camera +y goes up
    d_cam = torch.stack([x, y, -torch.ones_like(x)], dim=-1)  # [B, H, W, 3]
    norm = d_cam.norm(dim=-1, keepdim=True)
    d_cam = d_cam / norm
    dirs = torch.einsum("bij,bhwj->bhwi", c2w[:, :3, :3], d_cam)
    origins = c2w[:, None, None, :3, 3].expand_as(dirs)
    z_scale = 1.0 / norm[..., 0]  # cos of the angle to the optical axis
    return origins.contiguous(), dirs.contiguous(), z_scale


def load_transforms(
    path: str | os.PathLike[str],
) -> tuple[np.ndarray, np.ndarray, tuple[float, float, float, float], int, int, np.ndarray | None]:
    """Read a ``transforms.json`` (a file, or a capture folder meaning its ``transforms.json``).

    Returns:
        images: [N, H, W, 4] uint8 RGBA (RGB images get alpha 255).
        c2w: [N, 4, 4] float32 camera-to-world, OpenGL convention, metres.
        intrinsics: ``(fx, fy, cx, cy)`` in pixels (from fl_x/fl_y/cx/cy, or camera_angle_x).
        w, h: image size in pixels.
        depth: [N, H, W] float32 z-depth metres (0 = empty) when every frame has ``depth_file_path``, else None.

    Raises a one-line TnfError naming the file (and the frame) for anything unusable, a ``transform_matrix``
    that is not a rigid pose included (:func:`pose_problem`: scaled, sheared, mirrored, or a last row other
    than [0, 0, 0, 1]).
    """
    path = Path(path)
    if path.is_dir():
        path = path / "transforms.json"
    meta = _read_meta(path)
    w, h = _field(meta, "w", path, int), _field(meta, "h", path, int)
    intrinsics = _intrinsics(meta, path, w, h)
    frames = meta["frames"]
    if not isinstance(frames, list):
        raise TnfError(f"{path}: 'frames' must be a list of frames, got {type(frames).__name__}")
    if not frames:
        raise TnfError(f"{path}: 'frames' is empty")
    images, poses, depths = [], [], []
    for i, fr in enumerate(frames):
        if not isinstance(fr, dict):
            raise TnfError(f"{path}: frame {i} must be an object with file_path and transform_matrix")
        for key in ("file_path", "transform_matrix"):
            if key not in fr:
                raise TnfError(f"{path}: frame {i} is missing key {key!r}")
        m, rel = _frame_pose(fr, i, path)
        images.append(_frame_image(path, rel, i, w, h))
        poses.append(m)
        if "depth_file_path" in fr:
            depths.append(_frame_depth(path.parent / _rel_path(fr, "depth_file_path", path, i), path, i, w, h))
    depth = np.stack(depths) if len(depths) == len(frames) else None
    return np.stack(images), np.stack(poses), intrinsics, w, h, depth


def _read_meta(path: Path) -> dict[str, Any]:
    """The JSON object of the transforms file ``path``, checked to hold ``w``, ``h`` and ``frames``."""
    if not path.is_file():
        raise TnfError(f"transforms file not found: {path}")
    try:
        meta = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise TnfError(f"{path} is not valid JSON: {e}") from None
    if not isinstance(meta, dict):
        raise TnfError(f"{path}: expected a JSON object with w, h and frames, got {type(meta).__name__}")
    for key in ("w", "h", "frames"):
        if key not in meta:
            raise TnfError(f"{path}: missing key {key!r}")
    return meta


def _intrinsics(meta: dict[str, Any], path: Path, w: int, h: int) -> tuple[float, float, float, float]:
    """``(fx, fy, cx, cy)`` in pixels of a ``w`` x ``h`` image: from ``fl_x``/``fl_y`` or ``camera_angle_x``/
    ``camera_angle_y`` (radians; fy = fx when only x is given), the principal point the image centre unless
    ``cx``/``cy`` are given."""
    if "fl_x" in meta:
        fx = _field(meta, "fl_x", path)
        fy = _field(meta, "fl_y", path) if "fl_y" in meta else fx
    elif "camera_angle_x" in meta:
        ax = _field(meta, "camera_angle_x", path, limit=math.pi)
        fx = w / 2 / math.tan(ax / 2)
        fy = (
            h / 2 / math.tan(_field(meta, "camera_angle_y", path, limit=math.pi) / 2)
            if "camera_angle_y" in meta
            else fx
        )
    else:
        raise TnfError(f"{path}: missing key 'fl_x' or 'camera_angle_x' (the focal length)")
    cx = _field(meta, "cx", path, positive=False) if "cx" in meta else w / 2
    cy = _field(meta, "cy", path, positive=False) if "cy" in meta else h / 2
    return fx, fy, cx, cy


def _frame_pose(fr: dict[str, Any], i: int, path: Path) -> tuple[np.ndarray, str]:
    """Frame ``i``'s ``transform_matrix`` as a [4, 4] float32 rigid camera-to-world pose, and its image's path
    relative to the transforms file ``path``."""
    try:
        m = np.asarray(fr["transform_matrix"], dtype=np.float32)
    except (ValueError, TypeError):
        raise TnfError(f"{path}: frame {i} transform_matrix is not a 4x4 matrix of numbers") from None
    if m.shape != (4, 4):
        raise TnfError(f"{path}: frame {i} transform_matrix has shape {list(m.shape)}, expected [4, 4]")
    if not np.isfinite(m).all():
        raise TnfError(f"{path}: frame {i} transform_matrix holds NaN or infinite values")
    rel = _rel_path(fr, "file_path", path, i)
    problem = pose_problem(m)
    if problem is not None:
        raise TnfError(f"{path}: frame {i} ({rel!r}) transform_matrix is not a rigid camera pose: {problem}")
    return m, rel


def _frame_image(path: Path, rel: str, i: int, w: int, h: int) -> np.ndarray:
    """Frame ``i``'s image ``rel`` (relative to the transforms file ``path``; ``.png`` when it names no extension
    and no such file exists) as [h, w, 4] uint8 RGBA."""
    img_path = path.parent / rel
    if not img_path.suffix and not img_path.is_file():
        img_path = img_path.with_suffix(".png")  # instant-ngp files may omit the extension
    if not img_path.is_file():
        shown = str(img_path) if str(img_path).isprintable() else repr(str(img_path))  # one line, whatever the name
        raise TnfError(f"{path}: frame {i} image not found: {shown}")
    arr = _read_image(img_path)
    if arr.shape[:2] != (h, w):
        raise TnfError(f"{img_path}: image is {arr.shape[1]}x{arr.shape[0]}, transforms file says {w}x{h}")
    return arr


def _frame_depth(dp: Path, path: Path, i: int, w: int, h: int) -> np.ndarray:
    """Frame ``i``'s depth file ``dp`` (``.npy``) as [h, w] float32 z-depth, metres."""
    if not dp.is_file():
        raise TnfError(f"{path}: frame {i} depth file not found: {dp}")
    try:
        d = np.load(dp).astype(np.float32)
    except (OSError, ValueError, TypeError, EOFError) as e:  # not .npy, pickled objects, truncated
        raise TnfError(f"{dp}: not a readable depth array (.npy float): {e}") from None
    if d.shape != (h, w):
        raise TnfError(f"{dp}: depth is {list(d.shape)}, expected [{h}, {w}]")
    return d


# A camera pose's rotation may deviate this much from orthonormal (max |R^T R - I|) and its last row this much
# from [0, 0, 0, 1]. Poses tnf writes are rigid to float32 rounding (~1e-7); a 4-decimal JSON export is ~1e-4.
POSE_ROTATION_TOL = 1e-3
POSE_LAST_ROW_TOL = 1e-6


def pose_problem(m: np.ndarray) -> str | None:
    """What makes the finite 4x4 matrix ``m`` not a rigid transform (rotation + translation), or None.

    Checks the last row against [0, 0, 0, 1] (within ``POSE_LAST_ROW_TOL``) and the 3x3 part for unit-length,
    orthogonal columns (max |R^T R - I| within ``POSE_ROTATION_TOL``) and a positive determinant (no reflection).
    """
    m = np.asarray(m, dtype=np.float64)
    if np.abs(m[3] - (0.0, 0.0, 0.0, 1.0)).max() > POSE_LAST_ROW_TOL:
        return f"its last row is {_fmt(m[3])}, expected [0, 0, 0, 1]"
    r = m[:3, :3]
    gram, tol = r.T @ r, POSE_ROTATION_TOL
    problems = []
    if np.abs(np.diag(gram) - 1).max() > tol:
        problems.append(f"columns not unit length (lengths {_fmt(np.sqrt(np.diag(gram)))}, tolerance {tol:g}: scaled)")
    off = float(np.abs(gram - np.diag(np.diag(gram))).max())
    if off > tol:
        problems.append(f"columns not orthogonal (largest dot product {off:.3g}, tolerance {tol:g}: sheared)")
    det = float(np.linalg.det(r))
    if det < 0:
        problems.append(f"a reflection (det {det:.3g}: a mirrored axis)")
    if problems:
        return f"not a rotation: {', '.join(problems)}"
    return None


def _fmt(values: np.ndarray) -> str:
    return "[" + ", ".join(f"{float(x):.4g}" for x in values) + "]"


def _field(meta: dict[str, Any], key: str, path: Path, kind: type = float, positive: bool = True, limit=None) -> Any:
    """``meta[key]`` as a finite number (``kind``: int or float), > 0 when ``positive``, < ``limit`` if given."""
    value = meta[key]
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if ok and kind is int:
        ok = float(value).is_integer()
    if ok and positive:
        ok = value > 0
    if ok and limit is not None:
        ok = value < limit
    if not ok:
        what = "a positive integer" if kind is int else ("a positive number" if positive else "a finite number")
        raise TnfError(f"{path}: {key!r} must be {what}{f' below {limit:g}' if limit else ''}, got {value!r}")
    return kind(value)


def _rel_path(frame: dict[str, Any], key: str, path: Path, i: int) -> str:
    value = frame[key]
    if not isinstance(value, str) or not value or "\x00" in value:
        raise TnfError(f"{path}: frame {i} {key} must be a file path, got {value!r}")
    return value


def _read_image(img_path: Path) -> np.ndarray:
    """An RGB or RGBA image file as uint8 [H, W, 4] (RGB gets alpha 255)."""
    from PIL import Image

    try:
        with Image.open(img_path) as im:
            if im.mode not in ("RGB", "RGBA"):
                raise TnfError(f"{img_path}: expected an RGB or RGBA image, got mode {im.mode}")
            return np.asarray(im.convert("RGBA"))
    except (OSError, ValueError, Image.DecompressionBombError) as e:  # not an image, truncated, huge
        raise TnfError(f"{img_path}: not a readable image ({e})") from None


@dataclass(frozen=True, eq=False)
class Views:
    """Frames of one ``transforms.json`` (:func:`read_views`): numpy arrays on the CPU.

    Fields keep the precision the file is read at (``load_transforms``); :meth:`rgba` and :meth:`cameras`
    give the float32 tensors that scene fitting takes.
    """

    images: np.ndarray
    """[N, H, W, 4] uint8 RGBA."""
    c2w: np.ndarray
    """[N, 4, 4] float64 camera-to-world (OpenGL: looks along -z, +y up), metres; the file's float32 values."""
    intrinsics: tuple[float, float, float, float]
    """``(fx, fy, cx, cy)`` in pixels, shared by every frame."""
    width: int
    height: int
    depth: np.ndarray | None
    """[N, H, W] float32 z-depth, metres, 0 where no object; None when the file has none."""
    frames: np.ndarray
    """[N] int64 index of each frame in its file."""

    def __len__(self) -> int:
        return len(self.images)

    def take(self, keep: np.ndarray) -> Views:
        """The frames that ``keep`` (a boolean mask or indices into the N frames) selects."""
        depth = self.depth[keep] if self.depth is not None else None
        return Views(
            self.images[keep], self.c2w[keep], self.intrinsics, self.width, self.height, depth, self.frames[keep]
        )

    def rgba(self) -> torch.Tensor:
        """[N, H, W, 4] float32 RGBA in [0, 1]."""
        import torch

        return torch.from_numpy(self.images).float() / 255.0

    def cameras(self) -> tuple[torch.Tensor, torch.Tensor]:
        """c2w [N, 4, 4] float32 (metres) and intrinsics [N, 4] float32 ``(fx, fy, cx, cy)`` pixels."""
        import torch

        return torch.from_numpy(self.c2w).float(), torch.tensor([self.intrinsics] * len(self), dtype=torch.float32)


def read_views(path: str | os.PathLike[str], limit: int | None = None) -> Views:
    """The first ``limit`` (default all) frames of a ``transforms.json``-style file (``load_transforms``)."""
    images, c2w, intr, w, h, depth = load_transforms(path)
    n = min(limit, len(images)) if limit else len(images)
    return Views(
        images=images[:n],
        c2w=np.asarray(c2w[:n], dtype=np.float64),
        intrinsics=intr,
        width=int(w),
        height=int(h),
        depth=depth[:n] if depth is not None else None,
        frames=np.arange(n),
    )
