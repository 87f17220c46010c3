"""torch-scatter's ``scatter_min`` written with torch's own ``scatter_reduce_``, for Taxim's torch backend.

Taxim's torch backend imports ``torch_scatter`` for one call: ``scatter_min(src, index, dim_size=..., out=out)``
when it casts shadows. PyPI ships torch-scatter as source only, and a build must match the installed torch and
its CUDA. ``install()`` puts this module in its place when torch-scatter is not installed, so Taxim's torch backend
runs on any torch. bench/peers.py names the substitute in its rows.
"""

from __future__ import annotations

import sys
import types

import torch


def scatter_min(
    src: torch.Tensor,
    index: torch.Tensor,
    dim: int = -1,
    out: torch.Tensor | None = None,
    dim_size: int | None = None,
) -> tuple[torch.Tensor, None]:
    """Minimum of ``src`` over equal ``index`` along ``dim``, into ``out`` (its values take part) or a new tensor.

    ``index`` is 1-D along ``dim`` or has ``src``'s shape. A new ``out`` has ``dim_size`` entries along ``dim``
    (default ``index.max() + 1``) and is 0 where no entry lands, as torch-scatter's. Returns ``(out, None)``: no
    argmin, which Taxim does not read.
    """
    dim = dim % src.dim()
    if index.dim() == 1:
        shape = [1] * src.dim()
        shape[dim] = -1
        index = index.view(shape).expand_as(src)
    if out is None:
        size = list(src.shape)
        size[dim] = dim_size if dim_size is not None else int(index.max()) + 1 if index.numel() else 0
        out = torch.zeros(size, dtype=src.dtype, device=src.device)
        out.scatter_reduce_(dim, index, src, reduce="amin", include_self=False)
        return out, None
    out.scatter_reduce_(dim, index, src, reduce="amin", include_self=True)
    return out, None


def install() -> str:
    """Make ``import torch_scatter`` work: the installed package if there is one, else this module's substitute.

    Returns which: ``"torch-scatter X.Y.Z"`` or ``"scatter_reduce"``.
    """
    try:
        import torch_scatter

        if torch_scatter.scatter_min is scatter_min:  # installed here before
            return "scatter_reduce"
        return f"torch-scatter {torch_scatter.__version__}"
    except ImportError:
        module = types.ModuleType("torch_scatter")
        module.scatter_min = scatter_min  # type: ignore[attr-defined]
        sys.modules["torch_scatter"] = module
        return "scatter_reduce"
