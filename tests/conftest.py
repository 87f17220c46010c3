import os
from pathlib import Path

# Before anything imports OpenGL or warp: headless rendering, a stable kernel cache, few threads.
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
os.environ.setdefault("PYGLET_HEADLESS", "true")
os.environ.setdefault("WARP_CACHE_PATH", str(Path(__file__).resolve().parents[1] / ".warp-cache"))
os.environ.setdefault("WANDB_MODE", "offline")

import pytest  # noqa: E402

ASSETS = Path(__file__).resolve().parent / "assets"


@pytest.fixture
def data_root(tmp_path, monkeypatch):
    """A fresh artifact root for one test (also exported as TNF_DATA)."""
    root = tmp_path / "tnf-data"
    monkeypatch.setenv("TNF_DATA", str(root))
    return root
