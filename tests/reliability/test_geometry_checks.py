"""Geometry that cannot be right is refused with one line naming where it is: camera poses in a user's
``transforms.json`` that are not rigid (scaled, sheared, mirrored, a wrong last row), and meshes whose size is
implausible for a tabletop object (a unit mix-up). CPU only, no rendering."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest
import trimesh

from tests.objects.test_captured import small_dataset
from tests.reliability.helpers import assert_nothing_written, finished_items
from tnf.cameras import POSE_ROTATION_TOL, load_transforms, pose_problem
from tnf.capture import CaptureConfig, camera_poses
from tnf.cli import main
from tnf.errors import TnfError
from tnf.objects import WARN_SIZE
from tnf.registry import OBJECTS

BAD = 2  # the frame that gets the bad pose (not the first, so that the index in the message is checked)


def _edit_pose(folder, edit) -> None:
    """Replace frame ``BAD``'s transform_matrix of ``folder/transforms.json`` by ``edit(matrix)``."""
    meta = json.loads((folder / "transforms.json").read_text())
    m = np.array(meta["frames"][BAD]["transform_matrix"], dtype=np.float64)
    meta["frames"][BAD]["transform_matrix"] = np.asarray(edit(m), dtype=np.float64).tolist()
    (folder / "transforms.json").write_text(json.dumps(meta))


def _scaled(m):
    m[:3, :3] *= 2
    return m


def _sheared(m):
    # Unit-length columns 30 degrees apart instead of 90: only orthogonality fails.
    m[:3, 1] = np.cos(np.pi / 3) * m[:3, 0] + np.sin(np.pi / 3) * m[:3, 1]
    return m


def _reflected(m):
    m[:3, 0] *= -1
    return m


def _last_row(m):
    m[3] = [0, 0, 0.5, 1]
    return m


BAD_POSES = {
    "scaled": (_scaled, "columns not unit length (lengths [2, 2, 2]"),
    "sheared": (_sheared, "columns not orthogonal (largest dot product 0.5"),
    "reflection": (_reflected, "a reflection (det -1"),
    "last_row": (_last_row, "its last row is [0, 0, 0.5, 1], expected [0, 0, 0, 1]"),
}


@pytest.mark.parametrize("case", sorted(BAD_POSES))
def test_non_rigid_pose_is_refused_naming_the_frame(tmp_path, case):
    folder = small_dataset(tmp_path)
    edit, expected = BAD_POSES[case]
    _edit_pose(folder, edit)
    with pytest.raises(TnfError) as e:
        load_transforms(folder)
    msg = str(e.value)
    assert "\n" not in msg, msg
    assert str(folder / "transforms.json") in msg, msg
    assert f"frame {BAD} ('images/{BAD}.png')" in msg, msg
    assert "not a rigid camera pose" in msg and expected in msg, msg
    assert ("not a rotation" in msg) == (case != "last_row"), msg


def test_rigid_pose_with_float32_noise_is_accepted(tmp_path):
    folder = small_dataset(tmp_path)
    meta = json.loads((folder / "transforms.json").read_text())
    rng = np.random.default_rng(0)
    want = []
    for fr in meta["frames"]:
        m = np.array(fr["transform_matrix"])
        m[:3] += rng.uniform(-3e-7, 3e-7, (3, 4))  # a few float32 ulps, as poses written as float32 carry
        m = m.astype(np.float32)
        fr["transform_matrix"] = m.astype(np.float64).tolist()
        want.append(m)
    (folder / "transforms.json").write_text(json.dumps(meta))
    _, c2w, *_ = load_transforms(folder)
    np.testing.assert_array_equal(c2w, np.stack(want))
    # Within the tolerance passes, just outside it is refused.
    _edit_pose(folder, lambda m: np.diag([1 + POSE_ROTATION_TOL / 4] * 3 + [1]) @ m)
    load_transforms(folder)
    _edit_pose(folder, lambda m: np.diag([1 + POSE_ROTATION_TOL] * 3 + [1]) @ m)
    with pytest.raises(TnfError, match=f"frame {BAD} .*columns not unit length"):
        load_transforms(folder)


def test_poses_tnf_writes_are_rigid_in_float32():
    cfg = CaptureConfig(num_views=64, num_test_views=16, views="hemisphere")
    for radius in (0.001, 0.1, 5.0):
        for seed in range(3):
            for poses in camera_poses(radius, cfg, seed=seed) + camera_poses(radius, CaptureConfig(), seed=seed):
                assert len(poses)
                for m in poses:
                    assert pose_problem(m.astype(np.float32)) is None


def test_non_rigid_pose_fails_capture_and_writes_nothing(capsys, data_root, tmp_path):
    user = tmp_path / "user"
    small_dataset(user)
    _edit_pose(user / "cube", _reflected)
    capsys.readouterr()
    rc = main(["capture", "objects=captured", f"objects.root={user}", "progress=false"])
    err = capsys.readouterr().err
    assert rc == 1, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:"), err
    assert f"frame {BAD} ('images/{BAD}.png')" in lines[0] and "a reflection (det -1" in lines[0], err
    assert str(user / "cube" / "transforms.json") in lines[0], err
    assert_nothing_written(data_root, "capture")
    assert not list(data_root.rglob("manifest.json"))


# -- object sizes ------------------------------------------------------------------------------------------
def _box_obj(folder, name, size):
    folder.mkdir(parents=True, exist_ok=True)
    trimesh.creation.box(extents=[size, size, size]).export(folder / f"{name}.obj")


def test_mesh_of_100_m_is_refused_naming_size_and_scale(tmp_path, caplog):
    meshes = tmp_path / "meshes"
    _box_obj(meshes, "crate", 100.0)
    src = OBJECTS.build({"name": "mesh_dir", "path": str(meshes)})
    with pytest.raises(TnfError) as e:
        src.load("crate")
    msg = str(e.value)
    assert "\n" not in msg and str(meshes / "crate.obj") in msg and "'crate'" in msg, msg
    assert "100 m across" in msg and "objects.scale=1," in msg, msg
    assert "a mesh in millimetres needs objects.scale=0.001" in msg, msg
    assert src.load_or_skip("crate") is None  # skip_invalid (mesh_dir's default) skips it, saying why
    assert any("100 m across" in r.getMessage() for r in caplog.records)
    # In millimetres: 10 cm, loads without a warning.
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="tnf.objects"):
        mesh = OBJECTS.build({"name": "mesh_dir", "path": str(meshes), "scale": 0.001}).load("crate")
    np.testing.assert_allclose(mesh.extents, 0.1, rtol=1e-6)
    assert not caplog.records, [r.getMessage() for r in caplog.records]


def test_metre_mesh_read_as_millimetres_is_a_size_error_not_flat(tmp_path):
    meshes = tmp_path / "meshes"
    _box_obj(meshes, "cup", 0.08)
    src = OBJECTS.build({"name": "mesh_dir", "path": str(meshes), "scale": 0.001, "skip_invalid": False})
    with pytest.raises(TnfError) as e:
        src.load("cup")
    msg = str(e.value)
    assert "\n" not in msg and "'cup'" in msg and "8e-05 m across" in msg, msg
    assert "objects.scale=0.001" in msg and "objects.scale=1 makes it 0.08 m" in msg, msg
    assert "flat" not in msg, msg


def test_mesh_of_3_m_loads_with_a_warning(tmp_path, caplog):
    meshes = tmp_path / "meshes"
    _box_obj(meshes, "sofa", 3.0)
    _box_obj(meshes, "mug", 0.1)
    src = OBJECTS.build({"name": "mesh_dir", "path": str(meshes), "skip_invalid": False})
    with caplog.at_level(logging.WARNING, logger="tnf.objects"):
        mug = src.load("mug")
        assert not caplog.records, [r.getMessage() for r in caplog.records]
        sofa = src.load("sofa")
    np.testing.assert_allclose(sofa.extents, 3.0, rtol=1e-6)
    np.testing.assert_allclose(mug.extents, 0.1, rtol=1e-6)
    [rec] = caplog.records
    msg = rec.getMessage()
    assert rec.levelno == logging.WARNING and rec.name == "tnf.objects"
    assert "'sofa'" in msg and "3 m across" in msg and "objects.scale=1" in msg and "\n" not in msg, msg


def test_builtin_size_errors_and_every_builtin_object_is_plausible(caplog):
    with caplog.at_level(logging.WARNING, logger="tnf.objects"):
        src = OBJECTS.build({"name": "builtin"})
        sizes = {n: float(src.load(n).extents.max()) for n in src.names()}
    assert not caplog.records, [r.getMessage() for r in caplog.records]
    assert all(WARN_SIZE[0] <= s <= 1.0 for s in sizes.values()), sizes  # the bearing ball is 5 mm
    assert min(sizes, key=sizes.__getitem__) == "bearing_ball"
    with pytest.raises(TnfError, match=r"builtin object 'mug'.* with objects.scale=1000, implausible"):
        OBJECTS.build({"name": "builtin", "scale": 1000.0}).load("mug")


def test_oversized_mesh_fails_capture_and_writes_nothing(capsys, data_root, tmp_path):
    meshes = tmp_path / "meshes"
    _box_obj(meshes, "crate", 100.0)
    capsys.readouterr()
    rc = main(["capture", "objects=mesh_dir", f"objects.path={meshes}", "object=crate", "progress=false"])
    err = capsys.readouterr().err
    assert rc == 1, err
    errors = [ln for ln in err.splitlines() if ln.startswith("error:")]
    assert len(errors) == 1 and "'crate' is 100 m across" in errors[0] and "objects.scale=0.001" in errors[0], err
    assert finished_items(data_root, "capture") == []
    assert_nothing_written(data_root, "capture")
