"""tnf.cameras: look_at (a rigid pose looking at the target, its two fallbacks near ``up``) and Views."""

import json

import numpy as np
import pytest
import torch
from PIL import Image

from tnf.cameras import load_transforms, look_at, read_views
from tnf.errors import TnfError


@pytest.mark.parametrize("fallback", ["cone", "parallel"])
def test_look_at_is_a_rotation_looking_at_the_target(fallback):
    rng = np.random.default_rng(0)
    for _ in range(50):
        eye, target = rng.normal(size=3), rng.normal(size=3) * 0.1
        m = look_at(eye, target, fallback=fallback)
        r = m[:3, :3]
        np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-12)
        assert np.linalg.det(r) > 0
        view = (target - eye) / np.linalg.norm(target - eye)
        np.testing.assert_allclose(-m[:3, 2], view, atol=1e-12)
        np.testing.assert_array_equal(m[:3, 3], eye)
        assert m[:3, 0] @ [0.0, 0.0, 1.0] == pytest.approx(0.0, abs=1e-12)  # no roll: right is horizontal


def test_fallbacks_differ_only_close_to_up():
    one_degree = np.array([np.sin(np.radians(1.0)), 0.0, np.cos(np.radians(1.0))])
    cone, parallel = look_at(one_degree), look_at(one_degree, fallback="parallel")
    assert abs(cone[:3, 0] @ [0.0, 1.0, 0.0]) < 1e-12  # +y is up: right has no y
    assert abs(parallel[:3, 0] @ [0.0, 0.0, 1.0]) < 1e-12  # +z is still up
    overhead = np.array([0.0, 0.0, 1.0])
    np.testing.assert_array_equal(look_at(overhead), look_at(overhead, fallback="parallel"))
    far = np.array([1.0, 0.5, 0.3])
    np.testing.assert_array_equal(look_at(far), look_at(far, fallback="parallel"))


def test_unknown_fallback_is_refused():
    with pytest.raises(TnfError, match="fallback"):
        look_at([1.0, 0.0, 0.0], fallback="nearest")  # type: ignore[arg-type]


def _write_capture(folder, n=4, size=6):
    """A transforms.json of ``n`` frames with depth, and a focal length that float32 cannot hold exactly."""
    rng = np.random.default_rng(0)
    (folder / "images").mkdir()
    (folder / "depth").mkdir()
    frames = []
    for k in range(n):
        Image.fromarray(rng.integers(0, 256, (size, size, 4), dtype=np.uint8), "RGBA").save(folder / f"images/{k}.png")
        np.save(folder / f"depth/{k}.npy", rng.uniform(0.1, 0.3, (size, size)).astype(np.float32))
        eye = [0.3 * np.cos(k), 0.3 * np.sin(k), 0.1]
        frames.append(
            {
                "file_path": f"images/{k}.png",
                "depth_file_path": f"depth/{k}.npy",
                "transform_matrix": look_at(eye).tolist(),
            }
        )
    meta = {"fl_x": 7.123456789, "fl_y": 7.2, "cx": 3.0, "cy": 2.9, "w": size, "h": size, "frames": frames}
    (folder / "transforms.json").write_text(json.dumps(meta))
    return folder


def test_views_keep_the_files_precision_and_give_float32_tensors(tmp_path):
    folder = _write_capture(tmp_path)
    images, c2w, intrinsics, w, h, depth = load_transforms(folder)
    views = read_views(folder)
    assert len(views) == 4 and (views.width, views.height) == (w, h)
    np.testing.assert_array_equal(views.images, images)
    assert views.c2w.dtype == np.float64
    np.testing.assert_array_equal(views.c2w, c2w.astype(np.float64))
    assert views.intrinsics == (7.123456789, 7.2, 3.0, 2.9)  # Python floats: not rounded to float32
    np.testing.assert_array_equal(views.frames, np.arange(4))
    t_c2w, t_intrinsics = views.cameras()
    assert t_c2w.dtype == t_intrinsics.dtype == views.rgba().dtype == torch.float32
    assert torch.equal(t_c2w, torch.from_numpy(c2w))
    assert torch.equal(t_intrinsics, torch.tensor([intrinsics] * 4, dtype=torch.float32))
    assert torch.equal(views.rgba(), torch.from_numpy(images).float() / 255.0)


def test_views_select_frames(tmp_path):
    folder = _write_capture(tmp_path)
    views = read_views(folder)
    first = read_views(folder, limit=2)
    assert len(first) == 2 and first.depth is not None and views.depth is not None
    np.testing.assert_array_equal(first.depth, views.depth[:2])
    held = views.frames % 3 == 0
    test = views.take(held)
    np.testing.assert_array_equal(test.frames, [0, 3])
    np.testing.assert_array_equal(test.c2w, views.c2w[[0, 3]])
    np.testing.assert_array_equal(test.images, views.images[[0, 3]])
    assert test.depth is not None
    np.testing.assert_array_equal(test.depth, views.depth[[0, 3]])
    assert test.intrinsics == views.intrinsics
