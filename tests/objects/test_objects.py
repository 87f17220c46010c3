"""Object sources: the built-in library, mesh folders (YCB layout, textures outside the folder), validation."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from tnf.errors import TnfError
from tnf.objects import select, validate_mesh
from tnf.objects.builtin import MAKERS, Builtin
from tnf.registry import OBJECTS
from tnf.testing import compose

NAMES = sorted(MAKERS)


def test_library_has_enough_distinct_objects():
    assert len(NAMES) >= 30
    assert {"ball", "box"} <= set(NAMES)


@pytest.mark.parametrize("name", NAMES)
def test_builtin_object_is_a_valid_solid(name):
    mesh = Builtin().load(name)
    assert mesh.is_watertight, name
    assert mesh.volume > 0
    smallest = 0.005 if name == "bearing_ball" else 0.05  # the round indenter; every other object 5-25 cm
    assert smallest <= mesh.extents.max() <= 0.2501, mesh.extents
    assert np.allclose((mesh.vertices.min(0) + mesh.vertices.max(0)) / 2, 0, atol=1e-6)
    assert len(mesh.faces) <= 60_000
    assert mesh.visual.kind == "vertex"
    assert mesh.visual.vertex_colors[:, :3].std() > 0 or len(mesh.vertices) < 100


def test_builtin_is_deterministic_and_load_returns_copies():
    a, b = Builtin().load("bolt"), Builtin().load("bolt")
    assert a is not b
    np.testing.assert_array_equal(a.vertices, b.vertices)
    a.apply_translation([1, 0, 0])
    assert np.allclose(Builtin().load("bolt").vertices, b.vertices)


def test_objects_differ_in_shape():
    src = Builtin()
    sigs = {}
    for n in NAMES:
        m = src.load(n)
        sigs[n] = np.round(np.r_[np.sort(m.extents), m.volume * 1e6, m.area * 1e4], 2)
    arr = np.stack(list(sigs.values()))
    # No two objects share size, volume and area.
    d = np.abs(arr[:, None] - arr[None]).sum(-1) + np.eye(len(arr)) * 1e9
    assert d.min() > 0.05


def test_surface_detail_is_fingertip_scale():
    """Detailed objects deviate from their smooth envelope by millimetres (e.g. the bolt's thread)."""
    bolt = Builtin().load("bolt")
    r = np.hypot(bolt.vertices[:, 0], bolt.vertices[:, 1])
    shank = (bolt.vertices[:, 2] > bolt.vertices[:, 2].min() + 0.01) & (bolt.vertices[:, 2] < 0.0)
    relief = r[shank].max() - r[shank].min()
    assert 0.0008 < relief < 0.02


def test_scale_config_and_select(tmp_path):
    src = OBJECTS.build({"name": "builtin", "scale": 2.0})
    assert np.isclose(src.load("box").extents.max(), 2 * Builtin().load("box").extents.max())
    cfg = compose("capture", ["object=mug"])
    source, names = select(cfg.objects, cfg.object_names, cfg.object)
    assert source.name == "builtin" and names == ["mug"]
    assert select("builtin", ["box", "mug"], single="ball")[1] == ["ball"]  # one name wins over the list
    cfg = compose("capture", ["debug=tiny"])
    assert select(cfg.objects, cfg.object_names, cfg.object)[1] == ["ball", "box"]
    with pytest.raises(TnfError, match="unknown object 'teapot'.*available: apple"):
        select("builtin", single="teapot")
    with pytest.raises(TnfError, match="no objects selected from source 'builtin'"):
        select("builtin", [])


# -- validation ---------------------------------------------------------------------------------------------
def test_validate_rejects_bad_meshes():
    good = trimesh.creation.box([0.1, 0.1, 0.1])
    validate_mesh(good, "good.obj")
    nan = good.copy()
    v = nan.vertices.copy()
    v[0, 0] = np.nan
    nan.vertices = v
    with pytest.raises(TnfError, match="nan.obj: 1 vertices are NaN"):
        validate_mesh(nan, "nan.obj")
    with pytest.raises(TnfError, match="empty.obj: empty mesh"):
        validate_mesh(trimesh.Trimesh(np.zeros((3, 3)), np.zeros((0, 3), int)), "empty.obj")
    flat = trimesh.Trimesh([[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0], [0.1, 0.1, 0]], [[0, 1, 2], [1, 3, 2]])
    with pytest.raises(TnfError, match="flat.obj: degenerate"):
        validate_mesh(flat, "flat.obj")
    # A closed mesh whose two halves cancel: watertight, area > 0, volume 0.
    a = trimesh.creation.box([0.1, 0.1, 0.1])
    b = a.copy()
    b.invert()
    zero = trimesh.Trimesh(np.r_[a.vertices, b.vertices + [0.2, 0, 0]], np.r_[a.faces, b.faces + len(a.vertices)])
    if zero.is_watertight:
        with pytest.raises(TnfError, match="zero.obj: zero-volume"):
            validate_mesh(zero, "zero.obj")


# -- mesh_dir -----------------------------------------------------------------------------------------------
def _write_textured_obj(folder, texture_rel):
    """A textured cube OBJ whose MTL names its texture by ``texture_rel`` (relative to the OBJ's folder)."""
    from PIL import Image

    folder.mkdir(parents=True, exist_ok=True)
    tex = (folder / texture_rel).resolve()
    tex.parent.mkdir(parents=True, exist_ok=True)
    img = np.zeros((8, 8, 3), np.uint8)
    img[..., 0] = 200
    img[:4, :, 2] = 255
    Image.fromarray(img).save(tex)
    cube = trimesh.creation.box([0.06, 0.04, 0.05])
    lines = ["mtllib textured.mtl", "usemtl mat"]
    lines += [f"v {x} {y} {z}" for x, y, z in cube.vertices]
    lines += ["vt 0.1 0.1", "vt 0.9 0.1", "vt 0.5 0.9"]
    lines += [f"f {a + 1}/1 {b + 1}/2 {c + 1}/3" for a, b, c in cube.faces]
    (folder / "textured.obj").write_text("\n".join(lines) + "\n")
    (folder / "textured.mtl").write_text(f"newmtl mat\nKd 1 1 1\nmap_Kd {texture_rel}\n")


def test_mesh_dir_ycb_layout_with_texture_outside_folder(tmp_path):
    root = tmp_path / "ycb"
    _write_textured_obj(root / "003_cracker_box" / "google_16k", "../../textures/cracker.png")
    trimesh.creation.icosphere(2, radius=40.0).export(root / "balls" / "big.ply") if (
        root / "balls"
    ).mkdir() is None else None
    trimesh.creation.cylinder(radius=0.03, height=0.1).export(root / "can.stl")
    trimesh.creation.box([0.05, 0.08, 0.02]).export(root / "slab.glb")
    src = OBJECTS.build({"name": "mesh_dir", "path": str(root)})
    assert src.names() == ["003_cracker_box", "balls/big", "can", "slab"]
    box = src.load("003_cracker_box")
    assert box.visual.kind == "texture"
    assert box.visual.material.image is not None and box.visual.material.image.size == (8, 8)
    np.testing.assert_allclose(sorted(box.extents), [0.04, 0.05, 0.06], atol=1e-6)
    mm = OBJECTS.build({"name": "mesh_dir", "path": str(root), "scale": 0.001})
    np.testing.assert_allclose(mm.load("balls/big").extents, 0.08, rtol=0.02)
    y_up = OBJECTS.build({"name": "mesh_dir", "path": str(root), "up_axis": "y"})
    # The file's y axis becomes z, so the can's 0.1 m height (z in the file) now lies along y.
    np.testing.assert_allclose(y_up.load("can").extents, [0.06, 0.1, 0.06], atol=1e-3)


def test_mesh_dir_errors(tmp_path):
    with pytest.raises(TnfError, match="mesh folder not found"):
        OBJECTS.build({"name": "mesh_dir", "path": str(tmp_path / "nope")})
    with pytest.raises(TnfError, match="path is required"):
        OBJECTS.build({"name": "mesh_dir"})
    (tmp_path / "flat.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    (tmp_path / "nan.obj").write_text("v 0 0 nan\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 3 4\nf 1 4 2\nf 2 4 3\n")
    src = OBJECTS.build({"name": "mesh_dir", "path": str(tmp_path), "skip_invalid": False})
    with pytest.raises(TnfError, match=r"flat\.obj: degenerate"):
        src.load("flat")
    with pytest.raises(TnfError, match=r"nan\.obj: .*(NaN|empty)"):
        src.load("nan")
    with pytest.raises(TnfError, match="unknown object 'missing'"):
        src.load("missing")
    skipping = OBJECTS.build({"name": "mesh_dir", "path": str(tmp_path)})
    assert skipping.load_or_skip("flat") is None
    (tmp_path / "flat.obj").unlink()
    with pytest.raises(TnfError, match="mesh file not found"):
        src.load("flat")


@pytest.mark.parametrize("content", ["v 0\nf 0\n", "v 0\x1f0\nf 0\n", "v \nf 0\n"])
def test_mesh_files_with_malformed_vertices_are_clear_errors(tmp_path, content):
    # Found by the fuzz test: vertices without three coordinates crashed trimesh's processing or centring
    # (ValueError, OverflowError) in some trimesh versions instead of giving tnf's error.
    (tmp_path / "bad.obj").write_bytes(content.encode())
    src = OBJECTS.build({"name": "mesh_dir", "path": str(tmp_path), "skip_invalid": False})
    with pytest.raises(TnfError, match=r"bad\.obj"):
        src.load("bad")


def test_pybullet_source():
    pytest.importorskip("pybullet_data")
    src = OBJECTS.build({"name": "pybullet"})
    assert "duck" in src.names() and "random_000" in src.names()
    duck = src.load("duck")
    assert duck.visual.kind == "texture"
    blob = src.load("random_000")
    assert blob.visual.kind == "vertex"
    np.testing.assert_allclose(blob.visual.vertex_colors[0, :3] / 255, [0.04, 0.07, 0.91], atol=0.01)
    with pytest.raises(TnfError, match="168"):
        src.load("random_168")
    assert src.load_or_skip("random_168") is None


def test_objects_stage_lists(capsys, data_root):
    from tnf.cli import main

    assert main(["objects", "object_names=[ball,can]", "progress=false"]) == 0
    out = capsys.readouterr().out
    assert "ball" in out and "can" in out and "triangles" in out


def test_a_source_that_loads_a_scene_is_one_line():
    """A trimesh.Scene is what trimesh.load gives for a GLB or a multi-material OBJ: refused in one line naming the
    fix, not an AttributeError inside the centring."""
    from tnf.objects import ObjectSource

    class SceneSource(ObjectSource):
        name = "scenes"

        def names(self):
            return ["pair"]

        def _load(self, name):
            return trimesh.Scene([trimesh.creation.box((0.05, 0.05, 0.05)), trimesh.creation.icosphere()])

    with pytest.raises(TnfError, match=r"loaded a trimesh\.scene\.scene\.Scene, not a trimesh\.Trimesh; .*to_geometry"):
        SceneSource().load("pair")


@pytest.mark.parametrize(
    ("names", "error"),
    [
        ([], r"object source 'listing' lists no objects \(its names\(\) is empty\)"),
        ([1, "b"], r"object source 'listing': names\(\) must return a list of non-empty strings, got 1, 'b'"),
        ("ab", r"names\(\) must return a list of non-empty strings, got 'ab'"),
    ],
)
def test_a_source_whose_names_are_wrong_is_one_line(monkeypatch, names, error):
    """Before any selection: a source that lists nothing is not 'object_names is empty', and names that are not
    strings are not a TypeError deep in the selection."""
    from tnf.objects import ObjectSource

    class Listing(ObjectSource):
        def names(self):
            return names

    monkeypatch.setattr(OBJECTS, "build", lambda spec: Listing())
    for object_names in (None, ["b"]):
        with pytest.raises(TnfError, match=error):
            select("listing", object_names)
