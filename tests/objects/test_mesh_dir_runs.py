"""A folder of a user's meshes through the stages: nested names, invalid meshes, broken links, held-out objects."""

from __future__ import annotations

import logging
import os

import pytest
import trimesh

from tests.reliability.helpers import QUIET, finished_items, run_tnf
from tnf.artifacts import ArtifactStore
from tnf.data import choose_novel_objects
from tnf.errors import TnfError
from tnf.objects import select
from tnf.registry import OBJECTS
from tnf.stages.fit_scene import selected_objects
from tnf.testing import compose


@pytest.fixture
def meshes(tmp_path):
    """A box (OBJ) and, one folder down, a capsule (STL), in metres."""
    d = tmp_path / "meshes"
    (d / "tools").mkdir(parents=True)
    trimesh.creation.box((0.06, 0.04, 0.03)).export(d / "box.obj")
    trimesh.creation.capsule(height=0.05, radius=0.015).export(d / "tools" / "capsule.stl")
    return d


def source_args(folder) -> list[str]:
    return ["objects=mesh_dir", f"objects.path={folder}", "object_names=null"]


def test_fit_scene_finds_objects_in_subfolders(capsys, data_root, meshes):
    """fit-scene (and evaluate) find every captured object, ``tools/capsule`` included, not only top-level ones."""
    assert run_tnf(capsys, "capture", *QUIET, *source_args(meshes))[0] == 0
    cfg = compose("fit-scene", [*QUIET, *source_args(meshes), f"data_root={data_root}"])
    assert selected_objects(cfg, ArtifactStore(data_root), "mesh_dir") == ["box", "tools/capsule"]
    assert ArtifactStore(data_root).items("capture", "mesh_dir") == ["box", "tools/capsule"]


def test_touch_skips_an_invalid_mesh_as_capture_does(capsys, data_root, meshes):
    """objects.skip_invalid (the default) leaves an invalid mesh out of every stage, not of capture only."""
    (meshes / "points.obj").write_text("v 0 0 0\nv 0.05 0 0\nv 0 0.05 0\n")  # vertices, no faces
    rc, err = run_tnf(capsys, "touch", *QUIET, *source_args(meshes), "touch.n_touches=2", "touch.n_val=0")
    assert rc == 0, err
    touched = [
        p.relative_to(data_root / "touch" / "digit" / "mesh_dir").as_posix() for p in finished_items(data_root, "touch")
    ]
    assert touched == ["box", "tools/capsule"]


def test_only_invalid_meshes_is_one_line_error(capsys, data_root, tmp_path):
    d = tmp_path / "mm"
    d.mkdir()
    trimesh.creation.box((60.0, 40.0, 30.0)).export(d / "box_mm.stl")  # millimetres read as metres
    rc, err = run_tnf(capsys, "touch", *QUIET, *source_args(d))
    assert rc == 1 and err.startswith("error:") and "\n" not in err
    assert "box_mm.stl" in err and "objects.scale=0.001" in err


def test_objects_lists_and_fails_when_no_mesh_is_valid(capsys, data_root, tmp_path):
    d = tmp_path / "mm"
    d.mkdir()
    trimesh.creation.box((60.0, 40.0, 30.0)).export(d / "box_mm.stl")
    rc, err = run_tnf(capsys, "objects", *QUIET, *source_args(d))
    assert rc == 1 and err.startswith("error: no valid object:") and "\n" not in err and "objects.scale=0.001" in err
    trimesh.creation.box((0.06, 0.04, 0.03)).export(d / "box.obj")
    assert run_tnf(capsys, "objects", *QUIET, *source_args(d))[0] == 0


def test_broken_link_is_named(tmp_path, caplog):
    d = tmp_path / "links"
    d.mkdir()
    os.symlink(tmp_path / "gone.obj", d / "mug.obj")
    with pytest.raises(TnfError, match=r"no mesh files .* it holds only broken links \(1\)"):
        OBJECTS.build({"name": "mesh_dir", "path": str(d)})
    trimesh.creation.box((0.05, 0.05, 0.05)).export(d / "box.obj")
    with caplog.at_level(logging.WARNING):
        assert OBJECTS.build({"name": "mesh_dir", "path": str(d)}).names() == ["box"]
    assert "mug.obj: a broken symbolic link" in caplog.text


def test_folder_without_meshes_says_what_it_holds(tmp_path):
    (tmp_path / "mug.fbx").write_bytes(b"\0")
    (tmp_path / "notes.txt").write_text("")
    with pytest.raises(
        TnfError, match=r"it holds only \.fbx \(1\), \.txt \(1\)|it holds only \.txt \(1\), \.fbx \(1\)"
    ):
        OBJECTS.build({"name": "mesh_dir", "path": str(tmp_path)})


def test_unknown_object_says_how_to_choose(meshes):
    """The tiny and quick-start configs name built-in objects; on a user's folder the error says how to choose."""
    with pytest.raises(TnfError, match=r"unknown object 'ball'.*available: box, tools/capsule.*object_names=null"):
        select({"name": "mesh_dir", "path": str(meshes)}, ["ball", "box"])


def test_holding_out_every_object_is_refused():
    with pytest.raises(TnfError, match="num_novel_objects=1 holds out every selected object"):
        choose_novel_objects(["mug"], None, 1)
    with pytest.raises(TnfError, match="novel_objects holds out every selected object"):
        choose_novel_objects(["jar", "mug"], ["mug", "jar"])
    assert choose_novel_objects(["jar", "mug"], None, 1) in (["jar"], ["mug"])


def test_an_object_named_as_a_folder_of_others_is_refused(meshes):
    """``tools.obj`` beside ``tools/capsule.stl``: object ``tools``'s results would hold ``tools/capsule``'s."""
    trimesh.creation.box((0.05, 0.05, 0.05)).export(meshes / "tools.obj")
    with pytest.raises(TnfError, match=r"objects 'tools' .* and 'tools/capsule' .* would share a folder"):
        select(compose("objects", source_args(meshes)).objects, None)
