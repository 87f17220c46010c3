"""Scene representations that render RGB-D from any camera pose (``nerf``, ``hashgrid``, ``mesh``).

``load_scene(path)`` reads a fitted scene written by ``tnf fit-scene`` (``save_scene``). A checkpoint
stores the scene's registry name, its config as plain data and its tensors, never class paths, so code
can move without breaking old files.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

from tnf.artifacts import write_bytes
from tnf.errors import TnfError
from tnf.registry import SCENES, config_to_dict

if TYPE_CHECKING:
    from tnf.scenes.base import Scene

CHECKPOINT = "scene.pt"
FORMAT = "tnf-scene"
VERSION = 1


def save_scene(scene: Scene, path: str | os.PathLike[str], extra: dict[str, Any] | None = None) -> Path:
    """Write ``scene`` to ``path`` (a ``.pt`` file, or a folder that gets ``scene.pt``); returns the file.

    The scene must be a registered kind with a ``cfg`` Config; ``extra`` is plain data stored alongside.
    """
    import io

    import torch

    name = getattr(scene, "name", "") or _registered_name(scene)
    if name not in SCENES:
        raise TnfError(f"cannot save scene of unregistered kind {type(scene).__name__}")
    path = Path(path)
    if path.suffix != ".pt":
        path = path / CHECKPOINT
    blob = {
        "format": FORMAT,
        "version": VERSION,
        "name": name,
        "config": config_to_dict(scene.cfg),  # type: ignore[attr-defined]
        "state": {k: v.detach().cpu() for k, v in scene.state_dict().items()},
        "extra": dict(extra or {}),
    }
    buf = io.BytesIO()
    torch.save(blob, buf)
    write_bytes(path, buf.getvalue())
    return path


def load_scene(path: str | os.PathLike[str], device: str = "cpu") -> Scene:
    """A fitted scene from an item folder (with ``scene.pt``) or a ``scene.pt`` file, in eval mode on ``device``."""
    import pickle

    import torch

    path = Path(path)
    file = path / CHECKPOINT if path.is_dir() else path
    if not file.is_file():
        raise TnfError(f"scene checkpoint not found: {file}; run `tnf fit-scene` first")
    try:
        blob = torch.load(file, map_location="cpu", weights_only=True)
    except (pickle.UnpicklingError, RuntimeError, EOFError, OSError) as e:
        raise TnfError(f"{file} is not a readable scene checkpoint: {str(e).splitlines()[0]}") from None
    if not isinstance(blob, dict) or blob.get("format") != FORMAT:
        raise TnfError(f"{file} is not a tnf scene checkpoint (no format {FORMAT!r})")
    if blob.get("version") != VERSION:
        raise TnfError(f"{file}: scene checkpoint version {blob.get('version')!r}, this tnf reads {VERSION}")
    name = blob.get("name")
    if not isinstance(name, str) or name not in SCENES:
        raise TnfError(f"{file}: unknown scene kind {name!r}; available: {', '.join(SCENES.names())}")
    cfg = SCENES.config(name, blob.get("config", {}))
    scene = SCENES.get(name)(cfg)
    try:
        scene.load_state_dict(blob["state"])
    except (RuntimeError, KeyError) as e:
        raise TnfError(
            f"{file}: weights do not match a {name} scene with its config: {str(e).splitlines()[0]}"
        ) from None
    return scene.to(device).eval()


def checkpoint_extra(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The ``extra`` data stored with a scene checkpoint (folder or file)."""
    import torch

    path = Path(path)
    file = path / CHECKPOINT if path.is_dir() else path
    return dict(torch.load(file, map_location="cpu", weights_only=True).get("extra", {}))


def _registered_name(scene: Any) -> str:

    for e in SCENES.entries():
        if type(scene) is e.obj:
            return e.name
    return ""
