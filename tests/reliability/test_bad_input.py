"""Bad input through the real `tnf` command: one `error:` line naming what is wrong, exit code 1, nothing
left in the artifact store."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch
from PIL import Image

from tests.reliability.helpers import (
    QUIET,
    assert_nothing_written,
    cube_obj,
    finished_items,
    run_tnf,
    zero_volume_obj,
)


# -- meshes -----------------------------------------------------------------------------------------------
@pytest.fixture
def mesh_dir(tmp_path):
    d = tmp_path / "meshes"
    d.mkdir()
    (d / "good.obj").write_text(cube_obj())
    return d


def capture_mesh(capsys, mesh_dir, name, *extra):
    return run_tnf(capsys, "capture", *QUIET, "objects=mesh_dir", f"objects.path={mesh_dir}", f"object={name}", *extra)


BAD_MESHES = {
    "garbage.obj": (b"v 1 2\nf 1 2 3 4 5\n\x00\xff garbage", "cannot read mesh|empty mesh"),
    "garbage.ply": (
        b"ply\nformat binary_little_endian 1.0\nelement vertex 99\nend_header\n\x01\x02",
        "cannot read mesh",
    ),
    "garbage.stl": (b"solid x\nfacet normal 0 0 nan\nendsolid", "cannot read mesh|empty mesh"),
    "nan.obj": (cube_obj().replace("v -0.025 -0.025 -0.025", "v nan -0.025 -0.025").encode(), "NaN or infinite"),
    "nofaces.obj": ("".join(ln for ln in cube_obj().splitlines(True) if ln.startswith("v")).encode(), "empty mesh"),
    "flat.obj": (b"v 0 0 0\nv 0.05 0 0\nv 0 0.05 0\nv 0.05 0.05 0\nf 1 2 3\nf 2 4 3\n", "flat"),
    "zerovol.obj": (zero_volume_obj().encode(), "zero-volume"),
}


@pytest.mark.parametrize(
    "file,skip_invalid", [(f, True) for f in sorted(BAD_MESHES)] + [("nan.obj", False), ("zerovol.obj", False)]
)
def test_bad_mesh_is_one_line_error_and_writes_nothing(capsys, data_root, mesh_dir, file, skip_invalid):
    """Even with skip_invalid (the default), a run whose only object is broken fails: nothing was captured."""
    data, pattern = BAD_MESHES[file]
    (mesh_dir / file).write_bytes(data)
    name = file.rsplit(".", 1)[0]
    rc, err = capture_mesh(capsys, mesh_dir, name, f"objects.skip_invalid={str(skip_invalid).lower()}")
    assert rc == 1
    assert err.startswith("error:") and "\n" not in err
    assert str(mesh_dir / file) in err, err
    assert __import__("re").search(pattern, err), err
    assert_nothing_written(data_root, "capture")


def test_bad_mesh_among_good_ones_is_skipped(capsys, data_root, mesh_dir):
    (mesh_dir / "nan.obj").write_bytes(BAD_MESHES["nan.obj"][0])
    rc, _ = run_tnf(capsys, "capture", *QUIET, "objects=mesh_dir", f"objects.path={mesh_dir}", "object_names=null")
    assert rc == 0
    assert [p.name for p in finished_items(data_root, "capture")] == ["good"]


def test_missing_mesh_folder_and_unknown_object(capsys, data_root, mesh_dir, tmp_path):
    rc, err = run_tnf(capsys, "capture", *QUIET, "objects=mesh_dir", f"objects.path={tmp_path / 'nope'}")
    assert rc == 1 and "mesh folder not found" in err and str(tmp_path / "nope") in err
    rc, err = capture_mesh(capsys, mesh_dir, "missing")
    assert rc == 1 and "unknown object 'missing'" in err and "available: good" in err
    assert_nothing_written(data_root, "capture")


# -- registry names and config values -----------------------------------------------------------------------
def test_unknown_registry_name_lists_the_available_ones(capsys, data_root):
    rc, err = run_tnf(capsys, "touch", *QUIET, "sensor.name=gelsightx")
    assert rc == 1 and "unknown sensor 'gelsightx'" in err and "digit" in err and "omnitact" in err
    rc, err = run_tnf(capsys, "capture", *QUIET, "objects.name=nowhere")
    assert rc == 1 and "'nowhere'" in err and "builtin" in err and "mesh_dir" in err, err
    rc, err = run_tnf(capsys, "train", *QUIET, "generator.name=gan9000")
    assert rc == 1 and "gan9000" in err and "tn_cgan" in err
    rc, err = run_tnf(capsys, "capture", *QUIET, "sensor=gelsightx")  # a config group Hydra does not know
    assert rc == 1 and "gelsightx" in err and "digit" in err
    for stage in ("capture", "touch", "models"):
        assert_nothing_written(data_root, stage)


@pytest.mark.parametrize(
    "stage,override,expected",
    [
        ("touch", "touch.force=-1", "force must be in"),
        ("capture", "capture.resolution=0", "resolution must be in 8..4096 pixels, got 0"),
        ("capture", "capture.num_views=0", "num_views must be >= 1"),
        ("touch", "sensor.width=0", "sensor.digit: image size must be at least 8x8 pixels, got 0x80"),
        ("touch", "touch.radius=0", "touch.radius: must be > 0"),
        ("fit-scene", "fit.steps=-5", "steps"),
        ("fit-scene", "fit.batch_objects=0", "fit.batch_objects: must be >= 1, got 0"),
        ("finetune", "finetune.val_every_n_epochs=0", "finetune.val_every_n_epochs: must be >= 1, got 0"),
        ("train", "train.decay_epochs=9", "decay_epochs must be in [0, epochs=2], got 9"),
        ("train", "data.batch_size=0", "batch_size"),
    ],
)
def test_invalid_config_value(capsys, data_root, stage, override, expected):
    if stage == "train":
        write_dataset(data_root / "pairs" / "digit-hashgrid")
    rc, err = run_tnf(capsys, stage, *QUIET, override)
    assert rc == 1, err
    assert expected in err and err.count("\n") == 0, err
    for out in ("capture", "scenes", "touch", "models"):
        assert_nothing_written(data_root, out)


# -- transforms.json ---------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def captured(tmp_path_factory):
    """A real tiny capture of the builtin ball (shared read-only; tests copy it)."""
    from tnf.cli import main

    root = tmp_path_factory.mktemp("cap")
    mp = pytest.MonkeyPatch()
    mp.setenv("TNF_DATA", str(root))
    try:
        assert main(["capture", *QUIET, "object=ball", "capture.num_views=4", "capture.num_test_views=1"]) == 0
    finally:
        mp.undo()
    return root / "capture" / "builtin" / "ball"


def corrupt(meta: dict, folder, case: str) -> str:
    """Break one thing of a capture folder's transforms; returns the text the error must contain."""
    f0 = meta["frames"][0]
    if case == "no_frames":
        del meta["frames"]
        return "missing key 'frames'"
    if case == "no_focal":
        for k in ("fl_x", "fl_y", "camera_angle_x", "camera_angle_y"):
            meta.pop(k, None)
        return "missing key 'fl_x' or 'camera_angle_x'"
    if case == "no_matrix":
        del f0["transform_matrix"]
        return "frame 0 is missing key 'transform_matrix'"
    if case == "matrix_3x4":
        f0["transform_matrix"] = f0["transform_matrix"][:3]
        return "frame 0 transform_matrix has shape [3, 4], expected [4, 4]"
    if case == "matrix_ragged":
        f0["transform_matrix"][1] = [1, 2]
        return "frame 0 transform_matrix"
    if case == "matrix_nan":
        f0["transform_matrix"][0][3] = float("nan")
        return "frame 0 transform_matrix"
    if case == "w_text":
        meta["w"] = "wide"
        return "'w'"
    if case == "no_image":
        (folder / f0["file_path"]).unlink()
        return "frame 0 image not found"
    if case == "image_size":
        Image.new("RGBA", (10, 12)).save(folder / f0["file_path"])
        return "image is 10x12, transforms file says 64x64"
    if case == "image_gray":
        Image.new("L", (64, 64)).save(folder / f0["file_path"])
        return "expected an RGB or RGBA image, got mode L"
    if case == "image_corrupt":
        (folder / f0["file_path"]).write_bytes(b"\x89PNG\r\n\x1a\n broken")
        return "not a readable image"
    if case == "depth_shape":
        np.save(folder / f0["depth_file_path"], np.zeros((3, 3), np.float32))
        return "depth is [3, 3], expected [64, 64]"
    raise AssertionError(case)


CASES = [
    "no_frames", "no_focal", "no_matrix", "matrix_3x4", "matrix_ragged", "matrix_nan", "w_text", "no_image",
    "image_size", "image_gray", "image_corrupt", "depth_shape",
]  # fmt: skip


@pytest.mark.parametrize("case", CASES)
def test_bad_transforms_is_one_clear_error(tmp_path, captured, case):
    from tnf.cameras import load_transforms
    from tnf.errors import TnfError

    item = tmp_path / "ball"
    shutil.copytree(captured, item)
    meta = json.loads((item / "transforms.json").read_text())
    expected = corrupt(meta, item, case)
    (item / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(TnfError) as e:
        load_transforms(item)
    assert expected in str(e.value) and str(item) in str(e.value) and "\n" not in str(e.value)


@pytest.mark.parametrize("case", ["no_frames", "matrix_ragged", "no_image", "image_gray"])
def test_bad_transforms_fails_fit_scene_before_writing(capsys, data_root, captured, case):
    item = data_root / "capture" / "builtin" / "ball"
    shutil.copytree(captured, item)
    meta = json.loads((item / "transforms.json").read_text())
    expected = corrupt(meta, item, case)
    (item / "transforms.json").write_text(json.dumps(meta))
    rc, err = run_tnf(capsys, "fit-scene", *QUIET, "object=ball")
    assert rc == 1, err
    assert expected in err and err.count("\n") == 0, err
    assert str(item) in err, err
    assert_nothing_written(data_root, "scenes")


# -- pairing inputs ----------------------------------------------------------------------------------------
def test_pair_crop_larger_than_image_and_too_many_novel_objects(capsys, data_root):
    from tests.data.pair_inputs import make_inputs

    make_inputs(data_root, touches=3, size=64)
    rc, err = run_tnf(capsys, "pair", *QUIET, "pair.crop_px=100")
    assert rc == 1 and "crop of 100 px is larger than the 64x64 image" in err and "'ball'" in err, err
    rc, err = run_tnf(capsys, "pair", *QUIET, "pair.num_novel_objects=3")
    assert rc == 1 and "pair.num_novel_objects=3 but only 2 objects are selected" in err, err
    assert_nothing_written(data_root, "pairs")


def test_pair_broken_touch_manifest(capsys, data_root):
    from tests.data.pair_inputs import make_inputs

    make_inputs(data_root, touches=3, size=64)
    man = data_root / "touch" / "digit" / "builtin" / "box" / "manifest.json"
    m = json.loads(man.read_text())
    m["touches"][1]["start_c2w"] = [[1, 0, 0]]
    man.write_text(json.dumps(m))
    rc, err = run_tnf(capsys, "pair", *QUIET)
    assert rc == 1 and str(man) in err and "start_c2w" in err, err
    man.write_text("{not json")
    rc, err = run_tnf(capsys, "pair", *QUIET)
    assert rc == 1 and str(man) in err and "not valid JSON" in err, err
    assert_nothing_written(data_root, "pairs")


# -- datasets and checkpoints ------------------------------------------------------------------------------
def write_dataset(folder, n=6):
    from tests.generators.test_stages import write_pairs

    write_pairs(folder, n=n)


@pytest.mark.parametrize(
    "case,expected",
    [
        ("count", "manifest says 7 pairs"),
        ("objects", "object_id"),
        ("rows", "split.npy has 5 rows"),
        ("dtype", "rgb.npy"),
        ("missing", "tactile.npy is missing"),
        ("split_code", "split.npy"),
        ("background_index", "background_index"),
    ],
)
def test_dataset_whose_manifest_does_not_match_its_arrays(capsys, data_root, case, expected):
    from tnf.data import open_pairs
    from tnf.errors import TnfError

    folder = data_root / "pairs" / "digit-hashgrid"
    write_dataset(folder)
    man = json.loads((folder / "manifest.json").read_text())
    if case == "count":
        man["count"] = 7
    elif case == "objects":
        man["objects"] = ["ball"]  # object_id holds 0 and 1
    elif case == "rows":
        np.save(folder / "split.npy", np.zeros(5, np.int8))
    elif case == "dtype":
        np.save(folder / "rgb.npy", np.zeros((6, 128, 128, 3), np.float32))
    elif case == "missing":
        (folder / "tactile.npy").unlink()
    elif case == "split_code":
        np.save(folder / "split.npy", np.full(6, 9, np.int8))
    elif case == "background_index":
        np.save(folder / "background_index.npy", np.full(6, 3, np.int32))
    (folder / "manifest.json").write_text(json.dumps(man))
    with pytest.raises(TnfError, match=expected.replace(".", r"\.")):
        open_pairs(folder)
    if case not in ("count", "objects"):
        return  # the loader's error; two cases go through the command
    rc, err = run_tnf(capsys, "train", *QUIET)
    assert rc == 1, err
    assert expected in err and str(folder) in err and err.count("\n") == 0, err
    assert_nothing_written(data_root, "models")


def fake_checkpoint(path, generator="tn_cgan", fmt=None, state_of=None):
    """A generator checkpoint as `tnf train` writes it (the parts a loader reads)."""
    from tnf.generators.system import CHECKPOINT_FORMAT, GeneratorSystem, generator_spec

    system = GeneratorSystem({"name": state_of or generator, "ngf": 8, "ndf": 8}, epochs=2, decay_epochs=1)
    hp = dict(system.hparams)
    hp["generator"] = generator_spec({"name": generator, "ngf": 8, "ndf": 8})
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(
        {
            "state_dict": system.state_dict(),
            "hyper_parameters": hp,
            "tnf": {"format": fmt or CHECKPOINT_FORMAT, "kind": "generator", "generator": hp["generator"]},
        },
        path,
    )


@pytest.mark.parametrize(
    "case,expected",
    [
        ("version", "has format 99"),
        ("other_generator", "does not fit generator 'lee'"),
        ("not_generator", "is not a tnf generator checkpoint"),
        ("garbage", "cannot read generator checkpoint"),
    ],
)
def test_bad_checkpoint(capsys, data_root, case, expected):
    ckpt = data_root / "models" / "run" / "best.ckpt"
    if case == "version":
        fake_checkpoint(ckpt, fmt=99)
    elif case == "other_generator":  # weights of tn_cgan filed as lee
        fake_checkpoint(ckpt, generator="lee", state_of="tn_cgan")
    elif case == "not_generator":
        ckpt.parent.mkdir(parents=True)
        torch.save({"state_dict": {}, "scene": "hashgrid"}, ckpt)
    else:
        ckpt.parent.mkdir(parents=True)
        ckpt.write_bytes(b"PK\x03\x04 not really a zip")
    write_dataset(data_root / "pairs" / "omnitact-hashgrid")
    rc, err = run_tnf(capsys, "finetune", *QUIET, f"finetune.checkpoint={ckpt}", "data.datasets=[omnitact-hashgrid]")
    assert rc == 1 and expected in err and str(ckpt) in err and err.count("\n") == 0, err
    if case == "version":
        rc, err = run_tnf(capsys, "generate", *QUIET, "generate.model=run")
        assert rc == 1 and expected in err and str(ckpt) in err, err
    assert [p.name for p in finished_items(data_root, "models")] == []
    assert_nothing_written(data_root, "generated")
