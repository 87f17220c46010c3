"""The in-tree scenes pass the same contract suite as plugin scenes (tiny fields, few samples)."""

import pytest

from tnf.testing import SceneContract


class TestNerfContract(SceneContract):
    name = "nerf"
    params = {
        "depth": 2,
        "width": 16,
        "skip": 1,
        "pos_freqs": 2,
        "dir_freqs": 1,
        "samples_coarse": 8,
        "samples_fine": 8,
        "bound": 0.1,
    }


class TestHashGridContract(SceneContract):
    name = "hashgrid"
    params = {
        "levels": 2,
        "log2_table_size": 10,
        "max_resolution": 32,
        "hidden": 16,
        "samples_per_ray": 16,
        "occupancy_resolution": 8,
        "bound": 0.1,
    }


class TestMeshContract(SceneContract):
    name = "mesh"
    saveable = False  # a mesh scene is built from the object's mesh, which lives in the capture stage

    @pytest.fixture
    def scene(self):
        import trimesh

        from tnf.scenes.mesh import MeshScene

        sphere = trimesh.creation.icosphere(subdivisions=2, radius=0.04)
        sphere.visual.vertex_colors = [200, 80, 40, 255]
        return MeshScene.from_mesh(sphere)

    def test_sphere_is_seen(self, scene):
        import torch

        c2w, k = self.cameras(2)
        out = scene.render_rgbd(c2w, k, self.width, self.height)
        h, w = self.height // 2, self.width // 2
        near = out["depth"][:, h - 1 : h + 1, w - 1 : w + 1].flatten(1).min(1).values
        # The central rays meet the 4 cm sphere about where the view axis does; the corners see nothing.
        expected = c2w[:, :3, 3].norm(dim=1) - 0.04
        assert torch.allclose(near, expected, atol=0.004), (near, expected)
        assert out["opacity"][:, 0, 0].eq(0).all() and out["depth"][:, 0, 0].eq(0).all()
