# mypy: ignore-errors
# (Warp kernels use Warp's types in annotations and arithmetic, which mypy cannot check.)
"""Warp kernels of the hash grid: the hash encoding (for rendering, and with its table gradient for training),
and the march's sample selection.

The PyTorch ``HashEncoding.forward`` builds [P, L, 8] tensors of corner indices, weights and features for P
samples and L levels, about 2 kB of memory traffic per sample; this kernel reads the position and the
8 L table rows and writes the L * F outputs, one thread per sample and level. It computes the same
function (the same cells, the same hash, trilinear weights), so renders agree with the PyTorch encoding to
float rounding. ``hash_encode_trainable`` adds the gradient with respect to the table: one thread per sample
and level adds each output gradient times its corner weight into the 8 rows it read (atomic adds).

``march_select`` finds each ray's next occupied samples: one thread per ray steps along it, looking up the
occupancy grid, until it has K of them or leaves its range. The PyTorch form of the same selection builds
[rays, window] tensors of sample positions, cells, ranks and masks; this writes only the K chosen distances.

Both run on the CPU (Warp's LLVM backend) and CUDA, on torch tensors without copies.
"""

from __future__ import annotations

from typing import Any

import torch
import warp as wp

from tnf.runtime import init_warp

wp.set_module_options({"enable_backward": False})  # the table gradient is a kernel of its own (_encode_grad)


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


@wp.func
def _scaled(v: float, r: float) -> float:
    # A coordinate in cells of a level of r cells per axis, as in HashEncoding.forward.
    return wp.clamp(v, 0.0, 1.0) * r


@wp.func
def _cell(s: float, r: float) -> float:
    # The lowest corner of the cell holding s (the top face belongs to the last cell).
    return wp.min(wp.floor(s), r - 1.0)


@wp.func
def _corner_weight(x: wp.array2d(dtype=wp.float32), p: int, r: float, c: int) -> float:
    # The trilinear weight of corner c = (x bit 0, y bit 1, z bit 2) of sample p's cell at a level of r cells.
    sx = _scaled(x[p, 0], r)
    sy = _scaled(x[p, 1], r)
    sz = _scaled(x[p, 2], r)
    fx = sx - _cell(sx, r)
    fy = sy - _cell(sy, r)
    fz = sz - _cell(sz, r)
    w = wp.float32(1.0)
    if (c & 1) == 1:
        w = w * fx
    else:
        w = w * (1.0 - fx)
    if ((c >> 1) & 1) == 1:
        w = w * fy
    else:
        w = w * (1.0 - fy)
    if ((c >> 2) & 1) == 1:
        w = w * fz
    else:
        w = w * (1.0 - fz)
    return w


@wp.func
def _corner_table_row(
    x: wp.array2d(dtype=wp.float32),
    p: int,
    lvl: int,
    r: float,
    c: int,
    n_dense: int,
    table_size: int,
    rows: wp.array(dtype=wp.int32),
    use_rows: int,
):
    # The table row of corner c of sample p's cell at level lvl (r cells), its object's rows added.
    dense = wp.int32(0)
    if lvl < n_dense:
        dense = 1
    ix = int(_cell(_scaled(x[p, 0], r), r)) + (c & 1)
    iy = int(_cell(_scaled(x[p, 1], r), r)) + ((c >> 1) & 1)
    iz = int(_cell(_scaled(x[p, 2], r), r)) + ((c >> 2) & 1)
    row = lvl * table_size + _corner_row(ix, iy, iz, dense, int(r) + 1, table_size)
    if use_rows != 0:
        row = row + rows[p]
    return row


@wp.kernel
def _encode(
    x: wp.array2d(dtype=wp.float32),  # [P, 3] positions in [0, 1]^3
    table: wp.array2d(dtype=Any),  # [L * T, F] feature rows, float32 or float16
    res: wp.array(dtype=wp.float32),  # [L] cells per axis of each level
    n_dense: int,
    table_size: int,
    rows: wp.array(dtype=wp.int32),  # [P] rows added to every row sample p reads, or [1] ignored
    use_rows: int,
    out: wp.array2d(dtype=wp.float32),  # [P, L * F]
):
    p, lvl = wp.tid()
    r = res[lvl]
    F = table.shape[1]
    for f in range(F):
        acc = wp.float32(0.0)
        for c in range(8):
            row = _corner_table_row(x, p, lvl, r, c, n_dense, table_size, rows, use_rows)
            acc = acc + _corner_weight(x, p, r, c) * wp.float32(table[row, f])
        out[p, lvl * F + f] = acc


@wp.kernel
def _encode_grad(
    x: wp.array2d(dtype=wp.float32),  # [P, 3] positions in [0, 1]^3
    res: wp.array(dtype=wp.float32),  # [L] cells per axis of each level
    n_dense: int,
    table_size: int,
    rows: wp.array(dtype=wp.int32),  # [P] rows added to every row sample p reads, or [1] ignored
    use_rows: int,
    grad_out: wp.array2d(dtype=wp.float32),  # [P, L * F] gradient of the loss with respect to the features
    grad_table: wp.array2d(dtype=wp.float32),  # [rows, F] gradient with respect to the table, added to
):
    p, lvl = wp.tid()
    r = res[lvl]
    F = grad_table.shape[1]
    for c in range(8):
        row = _corner_table_row(x, p, lvl, r, c, n_dense, table_size, rows, use_rows)
        w = _corner_weight(x, p, r, c)
        for f in range(F):
            wp.atomic_add(grad_table, row, f, w * grad_out[p, lvl * F + f])


# Both table precisions compiled together (one module build instead of one per precision met).
for _dtype in (wp.float32, wp.float16):
    wp.overload(_encode, {"table": wp.array2d(dtype=_dtype)})


@wp.kernel
def _march_select(
    ray: wp.array2d(dtype=wp.float32),  # [A, >=9]: origin (3), direction (3), near, far, offset
    state: wp.array2d(dtype=wp.float32),  # [A, >=2]: next and end sample numbers; the next is advanced here
    occupied: wp.array(dtype=wp.uint8),  # [G^3] occupancy grid, x slowest
    grid: int,
    bound: float,
    dt: float,
    k_max: int,
    t_out: wp.array2d(dtype=wp.float32),  # [A, K] distances of the chosen samples (0 after the count)
    count: wp.array(dtype=wp.int32),  # [A] samples chosen
):
    a = wp.tid()
    ox = ray[a, 0]
    oy = ray[a, 1]
    oz = ray[a, 2]
    dx = ray[a, 3]
    dy = ray[a, 4]
    dz = ray[a, 5]
    near = ray[a, 6]
    far = ray[a, 7]
    off = ray[a, 8]
    j = int(state[a, 0])
    end = int(state[a, 1])
    scale = float(grid) / (2.0 * bound)
    n = int(0)  # noqa: UP018  (a typed variable: Warp lets loops reassign it)
    while j < end and n < k_max:
        t = near + (float(j) + off) * dt
        if t >= far:
            j = end
            break
        # The cell arithmetic of HashGridScene._cell_index (truncation toward zero, then clamped).
        cx = wp.clamp(int((ox + t * dx + bound) * scale), 0, grid - 1)
        cy = wp.clamp(int((oy + t * dy + bound) * scale), 0, grid - 1)
        cz = wp.clamp(int((oz + t * dz + bound) * scale), 0, grid - 1)
        if occupied[(cx * grid + cy) * grid + cz] != wp.uint8(0):
            t_out[a, n] = t
            n = n + 1
        j = j + 1
    for m in range(n, k_max):
        t_out[a, m] = 0.0
    count[a] = n
    state[a, 0] = float(j)


def march_select(
    ray: torch.Tensor, state: torch.Tensor, occupied: torch.Tensor, bound: float, dt: float, k: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """Each ray's next ``k`` occupied samples: distances [A, k] (0 where none) and counts [A] (int32).

    ``ray`` [A, >=9] float32: origin, direction, near, far and the sample offset (sample n at
    ``near + (n + offset) * dt``); ``state`` [A, >=2] float32: the next sample number, advanced in place past
    the last sample looked at, and the end; ``occupied`` [G^3] uint8. Samples at or beyond ``far`` are not
    taken (the ray's next number becomes its end). All on one device, contiguous.
    """
    init_warp()
    A = ray.shape[0]
    grid = round(occupied.numel() ** (1.0 / 3.0))
    t_out = torch.empty(A, k, device=ray.device, dtype=torch.float32)
    count = torch.empty(A, device=ray.device, dtype=torch.int32)
    if A == 0:
        return t_out, count
    args = [
        wp.from_torch(ray),
        wp.from_torch(state),
        wp.from_torch(occupied),
        int(grid),
        float(bound),
        float(dt),
        int(k),
        wp.from_torch(t_out),
        wp.from_torch(count),
    ]
    _launch(_march_select, A, args, ray)
    return t_out, count


def _launch(kernel: Any, dim: Any, args: list[Any], like: torch.Tensor) -> None:
    if like.is_cuda:
        # On PyTorch's current stream, so the kernel runs in order with the surrounding torch operations.
        stream = wp.stream_from_torch(torch.cuda.current_stream(like.device))
        wp.launch(kernel, dim=dim, inputs=args, device=stream.device, stream=stream)
    else:
        wp.launch(kernel, dim=dim, inputs=args, device="cpu")


def available(device: torch.device) -> bool:
    """Whether Warp runs on ``device`` here (the kernel compiles on its first launch)."""
    key = str(device)
    if key not in _OK:
        try:
            init_warp()
            wp.get_device(f"cuda:{device.index or 0}" if device.type == "cuda" else "cpu")
            _OK[key] = True
        except Exception:  # no usable Warp device: the PyTorch encoding is used instead
            _OK[key] = False
    return _OK[key]


_OK: dict[str, bool] = {}


CPU_SPLIT_MIN = 1 << 15
"""Samples below which a CPU encoding runs as one launch (splitting it costs more than it saves)."""
_CPU_LOADED: list[bool] = []


def hash_encode(
    x: torch.Tensor,
    table: torch.Tensor,
    resolutions: torch.Tensor,
    n_dense: int,
    table_size: int,
    threads: int | None = None,
) -> torch.Tensor:
    """Hash-grid features [P, L * F] (float32) at positions x [P, 3] in [0, 1]^3.

    ``table``: [L * T, F] float32 or float16 rows (level l's rows start at l * T); ``resolutions``: [L]
    float32 cells per axis; levels below ``n_dense`` are indexed directly, the others hashed into T rows.
    All tensors on one device (CPU or CUDA); nothing is differentiated. On the CPU, where one Warp launch runs
    on one core, ``threads`` launches (default: torch's thread count) each encode a block of samples at once;
    every sample's features are the same either way.
    """
    init_warp()  # once per process; a no-op after
    P, L, F = x.shape[0], resolutions.shape[0], table.shape[1]
    out = torch.empty(P, L * F, device=x.device, dtype=torch.float32)
    if P == 0:
        return out
    x = x.detach().float().contiguous()
    shared = [
        wp.from_torch(table.detach().contiguous()),
        wp.from_torch(resolutions.detach().float().contiguous()),
        int(n_dense),
        int(table_size),
        wp.from_torch(torch.zeros(1, dtype=torch.int32, device=x.device)),
        0,
    ]

    def encode(rows: slice) -> None:
        xs, outs = x[rows], out[rows]
        _launch(_encode, (xs.shape[0], L), [wp.from_torch(xs), *shared, wp.from_torch(outs)], x)

    n = 1 if x.is_cuda else min(threads or torch.get_num_threads(), P // CPU_SPLIT_MIN)
    if n <= 1:
        encode(slice(0, P))
        return out
    if not _CPU_LOADED:  # load (or compile) the module on this thread, not in several at once
        encode(slice(0, 1))
        _CPU_LOADED.append(True)
    from concurrent.futures import ThreadPoolExecutor

    edges = [P * k // n for k in range(n + 1)]
    with ThreadPoolExecutor(n) as pool:  # Warp releases the GIL while a CPU kernel runs
        list(pool.map(encode, [slice(a, b) for a, b in zip(edges[:-1], edges[1:], strict=True)]))
    return out


class _TrainableEncoding(torch.autograd.Function):
    """The hash encoding by ``_encode``, differentiable with respect to the table by ``_encode_grad``."""

    @staticmethod
    def forward(ctx: Any, table, x, resolutions, n_dense, table_size, rows):  # noqa: ANN001, ANN205
        P, L, F = x.shape[0], resolutions.shape[0], table.shape[1]
        out = torch.empty(P, L * F, device=x.device, dtype=torch.float32)
        ctx.save_for_backward(x, resolutions, rows)
        ctx.meta = (int(n_dense), int(table_size), tuple(table.shape))
        if P:
            args = [wp.from_torch(x), wp.from_torch(table.detach()), wp.from_torch(resolutions), int(n_dense)]
            args += [int(table_size), wp.from_torch(rows), 1, wp.from_torch(out)]
            _launch(_encode, (P, L), args, x)
        return out

    @staticmethod
    def backward(ctx: Any, grad):  # noqa: ANN001, ANN205
        x, resolutions, rows = ctx.saved_tensors
        n_dense, table_size, shape = ctx.meta
        grad_table = torch.zeros(shape, device=x.device, dtype=torch.float32)
        P, L = x.shape[0], resolutions.shape[0]
        if P:
            args = [wp.from_torch(x), wp.from_torch(resolutions), n_dense, table_size, wp.from_torch(rows)]
            args += [1, wp.from_torch(grad.float().contiguous())]
            _launch(_encode_grad, (P, L), [*args, wp.from_torch(grad_table)], x)
        return grad_table, None, None, None, None, None


def hash_encode_trainable(
    x: torch.Tensor,
    table: torch.Tensor,
    resolutions: torch.Tensor,
    n_dense: int,
    table_size: int,
    rows: torch.Tensor | None = None,
) -> torch.Tensor:
    """``hash_encode`` of a float32 ``table`` that training differentiates: features [P, L * F] at positions
    x [P, 3] in [0, 1]^3, with the gradient with respect to ``table`` (not to ``x``) in one kernel launch.

    ``rows``: [P] integer rows added to every row sample p reads (``HashEncoding.forward``'s ``offset``). The
    gradient's atomic adds make its float sums run in no fixed order on CUDA; on the CPU one launch runs on one
    core.
    """
    init_warp()
    if x.requires_grad:
        raise ValueError("hash_encode_trainable gives no gradient with respect to the positions x")
    if table.dtype != torch.float32:
        raise ValueError(f"hash_encode_trainable trains a float32 table, not {table.dtype}")
    if table.shape[0] > 2**31 - 1:
        raise ValueError(f"hash_encode_trainable indexes rows in int32: {table.shape[0]} rows are too many")
    x = x.detach().float().contiguous()
    if rows is None:
        rows = torch.zeros(x.shape[0], dtype=torch.int32, device=x.device)
    rows = rows.to(device=x.device, dtype=torch.int32).reshape(-1).contiguous()
    if rows.shape[0] != x.shape[0]:
        raise ValueError(f"rows has {rows.shape[0]} entries for {x.shape[0]} positions")
    res = resolutions.detach().float().contiguous()
    return _TrainableEncoding.apply(table.contiguous(), x, res, n_dense, table_size, rows)
