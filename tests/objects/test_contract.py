"""The in-tree object sources pass the same contract suite as a plugin's object source."""

import pytest

from tests.objects.test_captured import small_dataset
from tnf.registry import OBJECTS
from tnf.testing import ObjectSourceContract


class TestBuiltinContract(ObjectSourceContract):
    name = "builtin"


class TestPyBulletContract(ObjectSourceContract):
    name = "pybullet"
    params = {"include_random": False}


class TestMeshDirContract(ObjectSourceContract):
    name = "mesh_dir"
    params = {"path": "meshes", "scale": 0.001}

    @pytest.fixture(scope="class")
    @classmethod
    def source(cls, tmp_path_factory):
        import trimesh

        folder = tmp_path_factory.mktemp("meshes")
        trimesh.creation.box(extents=(40.0, 60.0, 20.0)).export(folder / "block.ply")  # millimetres
        trimesh.creation.icosphere(radius=25.0).export(folder / "ball.stl")
        return OBJECTS.build({**cls.spec(), "path": str(folder)})


class TestCapturedContract(ObjectSourceContract):
    name = "captured"
    params = {"root": "objects"}

    @pytest.fixture(scope="class")
    @classmethod
    def source(cls, tmp_path_factory):
        root = tmp_path_factory.mktemp("captured")
        small_dataset(root, "cube")
        return OBJECTS.build({**cls.spec(), "root": str(root)})
