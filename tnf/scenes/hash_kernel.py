# mypy: ignore-errors
# (Warp kernels use Warp's types in annotations and arithmetic, which mypy cannot check.)
"""The hash encoding's forward pass as one Warp kernel, for rendering (no gradients).

The PyTorch ``HashEncoding.forward`` builds [P, L, 8] tensors of corner indices, weights and features for P
samples and L levels, about 2 kB of memory traffic per sample; this kernel reads the position and the
8 L table rows and writes the L * F outputs, one thread per sample and level. It computes the same
function (the same cells, the same hash, trilinear weights), so renders agree with the PyTorch encoding to
float rounding. It runs on the CPU (Warp's LLVM backend) and CUDA, on torch tensors without copies.
"""

from __future__ import annotations

from typing import Any

import torch
import warp as wp

wp.set_module_options({"enable_backward": False})  # forward only: rendering takes no gradients


# Instant-NGP's spatial hash primes for y and z (x's is 1), as unsigned 32-bit constants.
_PRIME_Y = wp.constant(wp.uint32(2654435761))
_PRIME_Z = wp.constant(wp.uint32(805459861))


@wp.func
def _corner_row(ix: int, iy: int, iz: int, dense: int, stride: int, table_size: int) -> int:
    # Coarse levels are indexed directly, finer ones by the spatial hash (x * 1) ^ (y * p1) ^ (z * p2) mod T;
    # unsigned 32-bit products keep the low bits that PyTorch's wrapping int32 products keep.
    if dense != 0:
        return ix + iy * stride + iz * stride * stride
    h = wp.uint32(ix) ^ (wp.uint32(iy) * _PRIME_Y) ^ (wp.uint32(iz) * _PRIME_Z)
    return int(h & wp.uint32(table_size - 1))


@wp.kernel
def _encode(
    x: wp.array2d(dtype=wp.float32),  # [P, 3] positions in [0, 1]^3
    table: wp.array2d(dtype=Any),  # [L * T, F] feature rows, float32 or float16
    res: wp.array(dtype=wp.float32),  # [L] cells per axis of each level
    n_dense: int,
    table_size: int,
    out: wp.array2d(dtype=wp.float32),  # [P, L * F]
):
    p, lvl = wp.tid()
    r = res[lvl]
    # The cell and the position inside it per axis, as in HashEncoding.forward (the top face belongs to
    # the last cell).
    sx = wp.clamp(x[p, 0], 0.0, 1.0) * r
    sy = wp.clamp(x[p, 1], 0.0, 1.0) * r
    sz = wp.clamp(x[p, 2], 0.0, 1.0) * r
    bx = wp.min(wp.floor(sx), r - 1.0)
    by = wp.min(wp.floor(sy), r - 1.0)
    bz = wp.min(wp.floor(sz), r - 1.0)
    fx = sx - bx
    fy = sy - by
    fz = sz - bz
    ix = int(bx)
    iy = int(by)
    iz = int(bz)
    dense = wp.int32(0)
    if lvl < n_dense:
        dense = 1
    stride = int(r) + 1
    offset = lvl * table_size
    F = table.shape[1]
    for f in range(F):
        acc = wp.float32(0.0)
        for c in range(8):
            cx = c & 1
            cy = (c >> 1) & 1
            cz = (c >> 2) & 1
            w = wp.float32(1.0)
            if cx == 1:
                w = w * fx
            else:
                w = w * (1.0 - fx)
            if cy == 1:
                w = w * fy
            else:
                w = w * (1.0 - fy)
            if cz == 1:
                w = w * fz
            else:
                w = w * (1.0 - fz)
            row = offset + _corner_row(ix + cx, iy + cy, iz + cz, dense, stride, table_size)
            acc = acc + w * wp.float32(table[row, f])
        out[p, lvl * F + f] = acc


# Both table precisions compiled together (one module build instead of one per precision met).
for _dtype in (wp.float32, wp.float16):
    wp.overload(_encode, {"table": wp.array2d(dtype=_dtype)})


def available(device: torch.device) -> bool:
    """Whether Warp runs on ``device`` here (the kernel compiles on its first launch)."""
    key = str(device)
    if key not in _OK:
        try:
            wp.init()
            wp.get_device(f"cuda:{device.index or 0}" if device.type == "cuda" else "cpu")
            _OK[key] = True
        except Exception:  # no usable Warp device: the PyTorch encoding is used instead
            _OK[key] = False
    return _OK[key]


_OK: dict[str, bool] = {}


def hash_encode(
    x: torch.Tensor, table: torch.Tensor, resolutions: torch.Tensor, n_dense: int, table_size: int
) -> torch.Tensor:
    """Hash-grid features [P, L * F] (float32) at positions x [P, 3] in [0, 1]^3.

    ``table``: [L * T, F] float32 or float16 rows (level l's rows start at l * T); ``resolutions``: [L]
    float32 cells per axis; levels below ``n_dense`` are indexed directly, the others hashed into T rows.
    All tensors on one device (CPU or CUDA); nothing is differentiated.
    """
    wp.init()  # once per process; a no-op after
    P, L, F = x.shape[0], resolutions.shape[0], table.shape[1]
    out = torch.empty(P, L * F, device=x.device, dtype=torch.float32)
    if P == 0:
        return out
    x = x.detach().float().contiguous()
    table = table.detach().contiguous()
    args = [
        wp.from_torch(x),
        wp.from_torch(table),
        wp.from_torch(resolutions.detach().float().contiguous()),
        int(n_dense),
        int(table_size),
        wp.from_torch(out),
    ]
    if x.is_cuda:
        # On PyTorch's current stream, so the kernel runs in order with the surrounding torch operations.
        stream = wp.stream_from_torch(torch.cuda.current_stream(x.device))
        wp.launch(_encode, dim=(P, L), inputs=args, device=stream.device, stream=stream)
    else:
        wp.launch(_encode, dim=(P, L), inputs=args, device="cpu")
    return out
